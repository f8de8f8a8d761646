"""The ``shapes`` scorer (SYMSOL, SYMSOL-T, the toys): sample pose hypotheses for a test set and score
them per shape (spread, translation, coverage).

``evaluate(module, loader, shapes, ...)`` is what ``posediff fit`` runs at the end of training (and
the toy benchmark collects). It reports, per shape and overall:

* ``spread_deg`` — the paper's metric: mean over samples of the smallest angle to the set of
  equivalent ground-truth rotations (degrees);
* ``translation_error`` — mean distance of the sampled translations to the ground truth
  (groups with a translation);
* ``recall_rot@2/5/10`` — fraction of hypotheses within 2/5/10° of an equivalent rotation;
* ``recall_trans@0.02/0.05/0.1`` — fraction of hypotheses within that distance of the translation;
* ``coverage`` — fraction of the discrete equivalent poses with a sample within 5° (polyhedra);
* ``seconds_per_input`` — wall time of the sampler per test input (N hypotheses each).

The result after the last step is what is reported — never the best step along the trajectory.
"""

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch.utils.data import DataLoader

from ..diffusion import Sampler
from ..metrics import mode_coverage, recall, rotation_errors_deg, translation_errors
from ..module import PoseDiffusionModule
from ..symmetry import SHAPES, SYMSOL_LABELS, SymmetrySet, is_continuous
from .sampling import SampledBatches

#: recall thresholds (paper's SYMSOL-T evaluation: degrees, and scene units)
ROTATION_THRESHOLDS_DEG = (2.0, 5.0, 10.0)
TRANSLATION_THRESHOLDS = (0.02, 0.05, 0.1)


@torch.no_grad()
def evaluate(
    module: PoseDiffusionModule,
    loader: DataLoader,
    shapes: Sequence[str],
    *,
    num_samples: int = 200,
    num_steps: int | None = None,
    sampler: Sampler | None = None,
    seed: int = 0,
    coverage_threshold_deg: float = 5.0,
    rotation_thresholds_deg: Sequence[float] = ROTATION_THRESHOLDS_DEG,
    translation_thresholds: Sequence[float] = TRANSLATION_THRESHOLDS,
    max_inputs: int | None = None,
    symmetry_sets: Mapping[str, SymmetrySet] | None = None,
) -> dict[str, Any]:
    """Per-shape and overall metrics of ``num_samples`` hypotheses per test input (at most
    ``max_inputs`` inputs). Batches carry ``shape``, the index in ``posediff.symmetry.SYMSOL_LABELS``
    (SYMSOL I's five first); ``shapes`` orders the per-shape rows. ``symmetry_sets``: a shape's
    equivalents as its data gives them (the official SYMSOL files), else posediff's exact groups."""
    was_training = module.training
    module.eval()
    try:
        return _evaluate(
            module,
            loader,
            shapes,
            num_samples,
            num_steps,
            sampler,
            seed,
            coverage_threshold_deg,
            tuple(rotation_thresholds_deg),
            tuple(translation_thresholds),
            max_inputs,
            dict(symmetry_sets or {}),
        )
    finally:
        module.train(was_training)


def _evaluate(
    module: PoseDiffusionModule,
    loader: DataLoader,
    shapes: Sequence[str],
    num_samples: int,
    num_steps: int | None,
    sampler: Sampler | None,
    seed: int,
    coverage_threshold_deg: float,
    rotation_thresholds_deg: Sequence[float],
    translation_thresholds: Sequence[float],
    max_inputs: int | None,
    symmetry_sets: dict[str, SymmetrySet],
) -> dict[str, Any]:
    per_shape: dict[str, dict[str, list[torch.Tensor]]] = {}
    has_t = module.group.matrix_dim == 4
    run = SampledBatches(module, loader, num_samples, num_steps, sampler, seed, max_inputs)
    for batch, x in run:
        rot = x[..., :3, :3].double()
        for k in batch["shape"].unique().tolist():
            shape = SYMSOL_LABELS[k]
            sym = symmetry_sets.get(shape, shape)
            sel = batch["shape"] == k
            acc = per_shape.setdefault(shape, {"rot": [], "trans": [], "coverage": []})
            r_gt = batch["rotation"][sel].double()
            acc["rot"].append(rotation_errors_deg(sym, rot[sel], r_gt).cpu())
            # a continuous symmetry has no finite modes, whatever grid a file lists it on
            cov_sym = shape if shape in SHAPES and is_continuous(shape) else sym
            acc["coverage"].append(mode_coverage(cov_sym, rot[sel], r_gt, coverage_threshold_deg).cpu())
            if has_t:
                t_s, t_gt = x[sel][..., :3, 3].double(), batch["translation"][sel].double()
                acc["trans"].append(translation_errors(t_s, t_gt).cpu())
    result: dict[str, Any] = {"shapes": {}}
    order = [s for s in shapes if s in per_shape] + [s for s in per_shape if s not in shapes]
    for shape in order:
        acc = per_shape[shape]
        rot_err = torch.cat(acc["rot"])  # (inputs, N) degrees
        cov = torch.cat(acc["coverage"])
        row: dict[str, float] = {"inputs": float(rot_err.shape[0]), "spread_deg": float(rot_err.mean())}
        for thr, r in zip(
            rotation_thresholds_deg, recall(rot_err, rotation_thresholds_deg).tolist(), strict=True
        ):
            row[f"recall_rot@{_fmt_thr(thr)}"] = r
        if acc["trans"]:
            t_err = torch.cat(acc["trans"])
            row["translation_error"] = float(t_err.mean())
            for thr, r in zip(
                translation_thresholds, recall(t_err, translation_thresholds).tolist(), strict=True
            ):
                row[f"recall_trans@{_fmt_thr(thr)}"] = r
        row["coverage"] = float(cov.nanmean()) if not bool(cov.isnan().all()) else math.nan
        result["shapes"][shape] = row
    keys = [k for row in result["shapes"].values() for k in row if k != "inputs"]
    keys = list(dict.fromkeys(keys))
    result["overall"] = {k: _nanmean([row[k] for row in result["shapes"].values() if k in row]) for k in keys}
    result.update(run.summary())
    return result


def _fmt_thr(x: float) -> str:
    """``2.0 → "2"``, ``0.05 → "0.05"`` (metric names)."""
    return f"{x:g}"


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else math.nan


__all__ = ["ROTATION_THRESHOLDS_DEG", "TRANSLATION_THRESHOLDS", "evaluate"]
