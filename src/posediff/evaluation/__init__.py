"""Evaluation, one part: the shared sampling loop (:mod:`.sampling`), the scorers — per shape for the
toys and SYMSOL (:mod:`.shapes`), the BOP19 protocol for BOP datasets (:mod:`.bop`) — the reports
(:mod:`.report`) and prediction (:mod:`.predict`).

A data module says how its test split is scored through the small protocol of
:class:`posediff.data.PoseDataModule` (its ``scorer`` names one of :data:`SCORERS`), so that the
commands only instantiate and call :func:`evaluate_data` and :func:`write_results`; a new kind of
dataset adds a scorer here (:func:`register_scorer`) or reuses one (docs/extending.md, "How to add a dataset").
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..models import PoseDiffusionModule
from .bop import (
    best_hypothesis,
    check_estimates,
    estimates_of_predictions,
    evaluate_bop,
    predict_targets,
    score_estimates,
)
from .predict import (
    ImageError,
    Prediction,
    decode_prediction,
    image_tensor,
    load_image,
    predict,
    read_image,
    save_prediction,
)
from .report import ReportCallback, axis_table, collect_sweep, run_table, sweep_rows, sweep_table
from .sampling import SampledBatches
from .shapes import evaluate


def _score_shapes(module: Any, datamodule: Any, **kwargs: Any) -> dict[str, Any]:
    kwargs.pop("vsd", None)  # a BOP option
    if kwargs.get("log_likelihood") is None:  # auto: on for SO(3) data that asks for it (SYMSOL)
        kwargs["log_likelihood"] = bool(getattr(datamodule, "log_likelihood_default", False)) and (
            isinstance(module, PoseDiffusionModule)
        )
    sets = getattr(datamodule, "symmetry_sets", None)  # the official SYMSOL files' own equivalents
    return evaluate(module, datamodule.test_dataloader(), list(getattr(datamodule, "shapes", [])),
                    symmetry_sets=sets, **kwargs)  # fmt: skip


def _score_bop(module: Any, datamodule: Any, **kwargs: Any) -> dict[str, Any]:
    if kwargs.pop("log_likelihood", None):
        raise ValueError("log-likelihood is reported for SYMSOL, SYMSOL-T and the toys, not for BOP data "
                         "(set eval.log_likelihood=false)")  # fmt: skip
    kwargs.pop("log_likelihood_steps", None)
    return evaluate_bop(module, datamodule, **kwargs)


#: scorer name (a data module's ``scorer``) → ``f(module, datamodule, num_samples=, num_steps=,
#: sampler=, seed=, max_inputs=, vsd=) -> result dict``
SCORERS: dict[str, Callable[..., dict[str, Any]]] = {"shapes": _score_shapes, "bop": _score_bop}


def register_scorer(name: str, scorer: Callable[..., dict[str, Any]]) -> None:
    """Make ``scorer`` the scorer of data modules whose ``scorer`` is ``name``."""
    SCORERS[name] = scorer


def evaluate_data(module: Any, datamodule: Any, **kwargs: Any) -> dict[str, Any]:
    """Score ``module`` on ``datamodule``'s test split with the scorer the data module names."""
    name = getattr(datamodule, "scorer", "shapes")
    if name not in SCORERS:
        raise ValueError(
            f"{type(datamodule).__name__} asks for scorer {name!r}; known: {', '.join(sorted(SCORERS))}"
        )
    return SCORERS[name](module, datamodule, **kwargs)


def write_results(result: dict[str, Any], datamodule: Any, out_dir: Path, tag: str = "") -> Path | None:
    """Move an evaluation's estimates (``result["estimates"]``, BOP) into the results file the data
    module names (``datamodule.results_filename(tag)``, e.g. ``posediff-<tag>_tless-test.csv``); sets
    ``result["bop19_csv"]``. None when there is nothing to write."""
    rows = result.pop("estimates", None)
    name = datamodule.results_filename(tag) if hasattr(datamodule, "results_filename") else None
    if rows is None or name is None:
        return None
    from ..metrics.bop19 import write_bop19_csv

    path = write_bop19_csv(Path(out_dir) / name, rows)
    result["bop19_csv"] = str(path)
    return Path(path)


__all__ = [
    "SCORERS",
    "ImageError",
    "Prediction",
    "ReportCallback",
    "SampledBatches",
    "axis_table",
    "best_hypothesis",
    "check_estimates",
    "collect_sweep",
    "decode_prediction",
    "estimates_of_predictions",
    "evaluate",
    "evaluate_bop",
    "evaluate_data",
    "image_tensor",
    "load_image",
    "predict",
    "predict_targets",
    "read_image",
    "register_scorer",
    "run_table",
    "save_prediction",
    "score_estimates",
    "sweep_rows",
    "sweep_table",
    "write_results",
]
