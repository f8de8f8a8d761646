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
* ``seconds_per_input`` — wall time of the sampler per test input (N hypotheses each);
* with ``log_likelihood=True``: ``log_likelihood`` — the mean log density of the ground-truth
  rotation (rotation groups) under the model's probability-flow ODE
  (:func:`~posediff.diffusion.log_likelihood`), in Implicit-PDF's units: density with respect to the
  Haar measure of total volume π² (uniform = −ln π² ≈ −2.29; posediff's own measure has volume 8π²,
  so ``+ln 8``); for R³×SO(3) / SE(3) the ODE gives the joint density of rotation and translation
  (the rotation marginal is not available from it), reported as ``log_likelihood_joint`` (the same
  rotation measure × Lebesgue on the translation, scene units). ``log_likelihood_ode_error`` is
  the mean |difference| to the same ODE at half the steps (the integration error's size);
  ``result["log_likelihood"]`` holds the steps and the seconds per input. The ground truth is scored
  as the file gives it, not averaged over its equivalents (Implicit-PDF averages them; a
  symmetry-invariant model gives them the same density).

The result after the last step is what is reported — never the best step along the trajectory.
"""

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch.utils.data import DataLoader

from ..diffusion import Sampler, log_likelihood
from ..metrics import mode_coverage, recall, rotation_errors_deg, translation_errors
from ..models import PoseDiffusionModule, PoseModule
from ..symmetry import SHAPES, SYMSOL_LABELS, SymmetrySet, is_continuous
from .sampling import SampledBatches

#: recall thresholds (paper's SYMSOL-T evaluation: degrees, and scene units)
ROTATION_THRESHOLDS_DEG = (2.0, 5.0, 10.0)
TRANSLATION_THRESHOLDS = (0.02, 0.05, 0.1)
#: log(8π² / π²): posediff's Haar normalisation (volume 8π²) → Implicit-PDF's (volume π²)
LOG_IPDF_FROM_POSEDIFF = math.log(8.0)


@torch.no_grad()
def evaluate(
    module: PoseModule,
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
    log_likelihood: bool = False,
    log_likelihood_steps: int = 50,
) -> dict[str, Any]:
    """Per-shape and overall metrics of ``num_samples`` hypotheses per test input (at most
    ``max_inputs`` inputs). Batches carry ``shape``, the index in ``posediff.symmetry.SYMSOL_LABELS``
    (SYMSOL I's five first); ``shapes`` orders the per-shape rows. ``symmetry_sets``: a shape's
    equivalents as its data gives them (the official SYMSOL files), else posediff's exact groups.
    ``log_likelihood``: also the ground truth's log density (module docstring), by the ODE on
    ``log_likelihood_steps`` levels (and half as many, for the error estimate)."""
    if log_likelihood and not isinstance(module, PoseDiffusionModule):
        raise ValueError(
            "log-likelihood needs a diffusion model; this is a regression model (set eval.log_likelihood=false)"
        )
    if int(log_likelihood_steps) < 2:
        raise ValueError(f"eval.log_likelihood_steps must be at least 2, got {log_likelihood_steps}")
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
            int(log_likelihood_steps) if log_likelihood else 0,
        )
    finally:
        module.train(was_training)


def _evaluate(
    module: PoseModule,
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
    ll_steps: int,
) -> dict[str, Any]:
    per_shape: dict[str, dict[str, list[torch.Tensor]]] = {}
    has_t = module.group.matrix_dim == 4
    ll_key = "log_likelihood_joint" if has_t else "log_likelihood"
    ll_seconds = 0.0
    run = SampledBatches(module, loader, num_samples, num_steps, sampler, seed, max_inputs)
    for batch, x in run:
        rot = x[..., :3, :3].double()
        ll = ll_err = None
        if ll_steps:
            start = time.perf_counter()
            ll, ll_err = _ground_truth_log_density(module, batch, ll_steps)
            ll_seconds += time.perf_counter() - start
        for k in batch["shape"].unique().tolist():
            shape = SYMSOL_LABELS[k]
            sym = symmetry_sets.get(shape, shape)
            sel = batch["shape"] == k
            acc = per_shape.setdefault(
                shape, {"rot": [], "trans": [], "coverage": [], "ll": [], "ll_err": []}
            )
            if ll is not None and ll_err is not None:
                acc["ll"].append(ll[sel].cpu())
                acc["ll_err"].append(ll_err[sel].cpu())
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
        if acc["ll"]:
            row[ll_key] = float(torch.cat(acc["ll"]).mean())
            row["log_likelihood_ode_error"] = float(torch.cat(acc["ll_err"]).mean())
        result["shapes"][shape] = row
    keys = [k for row in result["shapes"].values() for k in row if k != "inputs"]
    keys = list(dict.fromkeys(keys))
    result["overall"] = {k: _nanmean([row[k] for row in result["shapes"].values() if k in row]) for k in keys}
    result.update(run.summary())
    if ll_steps:
        result["log_likelihood"] = {
            "key": ll_key,
            "steps": ll_steps,
            "check_steps": ll_steps // 2,
            "seconds_per_input": ll_seconds / max(run.count, 1),
            "measure": "Haar measure of volume π² (Implicit-PDF's; uniform = −2.29)"
            + (" × Lebesgue on the translation (joint density)" if has_t else ""),
        }
    return result


@torch.no_grad()
def _ground_truth_log_density(
    module: PoseDiffusionModule, batch: dict[str, Any], steps: int
) -> tuple[Any, Any]:
    """The log density of each input's ground-truth ``pose`` in Implicit-PDF's units ``(B,)``, and
    the |difference| to the ODE at half the steps ``(B,)``."""
    feature = module.encode(batch[module.cond_key])
    x = batch["pose"][:, None].to(feature.dtype)
    fn = module.denoise_fn()
    fine = log_likelihood(fn, module.diffusion, x, feature, num_steps=steps)
    coarse = log_likelihood(fn, module.diffusion, x, feature, num_steps=steps // 2)
    assert isinstance(fine, torch.Tensor) and isinstance(coarse, torch.Tensor)
    return fine[:, 0].double() + LOG_IPDF_FROM_POSEDIFF, (fine - coarse)[:, 0].abs().double()


def _fmt_thr(x: float) -> str:
    """``2.0 → "2"``, ``0.05 → "0.05"`` (metric names)."""
    return f"{x:g}"


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else math.nan


__all__ = ["LOG_IPDF_FROM_POSEDIFF", "ROTATION_THRESHOLDS_DEG", "TRANSLATION_THRESHOLDS", "evaluate"]
