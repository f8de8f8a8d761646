"""Sample pose hypotheses for a test set and score them per shape (spread, translation, coverage).

``evaluate(module, loader, shapes, ...)`` is what ``posediff fit`` runs at the end of training (and
the toy benchmark collects). It reports, per shape and overall:

* ``spread_deg`` — the paper's metric: mean over samples of the smallest angle to the set of
  equivalent ground-truth rotations (degrees);
* ``translation_error`` — mean distance of the sampled translations to the ground truth
  (groups with a translation);
* ``coverage`` — fraction of the discrete equivalent poses with a sample within 5° (polyhedra);
* ``seconds_per_input`` — wall time of the sampler per test input (N hypotheses each).

The result after the last step is what is reported — never the best step along the trajectory.
"""

import math
import time
from collections.abc import Sequence
from typing import Any

import torch
from torch.utils.data import DataLoader

from .diffusion import Sampler
from .metrics import mode_coverage, rotation_spread_deg, translation_error
from .module import PoseDiffusionModule


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
) -> dict[str, Any]:
    """Per-shape and overall metrics of ``num_samples`` hypotheses per test input."""
    was_training = module.training
    module.eval()
    try:
        return _evaluate(
            module, loader, shapes, num_samples, num_steps, sampler, seed, coverage_threshold_deg
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
) -> dict[str, Any]:
    gen = torch.Generator(device=module.device).manual_seed(int(seed))
    per_shape: dict[str, dict[str, list[torch.Tensor]]] = {}
    has_t = module.group.matrix_dim == 4
    seconds = 0.0
    count = 0
    for batch in loader:
        batch = {k: v.to(module.device) for k, v in batch.items()}
        start = time.perf_counter()
        x = module.sample(batch[module.cond_key], num_samples, num_steps, sampler=sampler, generator=gen)
        seconds += time.perf_counter() - start
        count += int(batch["pose"].shape[0])
        rot = x[..., :3, :3].double()
        for k in batch["shape"].unique().tolist():
            shape = shapes[k]
            sel = batch["shape"] == k
            acc = per_shape.setdefault(shape, {"spread_deg": [], "translation_error": [], "coverage": []})
            r_gt = batch["rotation"][sel].double()
            acc["spread_deg"].append(rotation_spread_deg(shape, rot[sel], r_gt))
            acc["coverage"].append(mode_coverage(shape, rot[sel], r_gt, coverage_threshold_deg))
            if has_t:
                acc["translation_error"].append(
                    translation_error(x[sel][..., :3, 3].double(), batch["translation"][sel].double())
                )
    result: dict[str, Any] = {"shapes": {}}
    for shape, acc in per_shape.items():
        row = {}
        for key, values in acc.items():
            if values:
                v = torch.cat(values)
                row[key] = float(v.nanmean()) if not bool(v.isnan().all()) else math.nan
        result["shapes"][shape] = row
    keys = ("spread_deg", "translation_error", "coverage")
    result["overall"] = {
        k: _nanmean([row[k] for row in result["shapes"].values() if k in row])
        for k in keys
        if any(k in row for row in result["shapes"].values())
    }
    result["seconds_per_input"] = seconds / max(count, 1)
    result["num_samples"] = int(num_samples)
    result["num_steps"] = num_steps
    return result


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else math.nan
