"""Evaluate a pose model on a BOP dataset: the BOP19 protocol and the paper's extra metrics in-process.

For every test target the data module yields (BOP19 targets: the ``inst_count`` most visible
instances of each target object, cropped from the ground-truth box and masked to the ground-truth
visible pixels, as the paper), the model samples ``num_samples`` poses; the first is the estimate
(the authors' evaluation: one hypothesis, score 1). It is decoded to the camera frame (mm) and
scored with :mod:`posediff.metrics.bop` / :mod:`posediff.metrics.bop19`:

* BOP19 average recalls ``AR_MSPD``, ``AR_MSSD``, ``AR_VSD`` and ``AR`` (VSD renders the model's
  depth at the estimated and the true pose with :class:`posediff.data.bop.render.BopRenderer`, and
  reads the test depth image; skipped when the bounding-sphere projections do not overlap);
* the paper's Table 3 recalls: symmetry-aware rotation ``R@2/5/10°``, translation ``T@2/5/10 cm`` and
  per-axis ``x/y/z@2/5/10 cm``.

Targets the data module dropped (no or too few visible pixels) count as misses. Each estimate is
paired with the target it was predicted for, so no matching is needed; the BOP19 CSV
(:func:`posediff.metrics.bop19.write_bop19_csv`) lets the official toolkit score the same estimates
with its own matching. Rows are per object (``obj_000001`` …), ``overall`` (recall over all
targets, as the toolkit) and ``object_mean`` (the mean of the object rows, the paper's "Avg(30)").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from .data.bop.datamodule import BopDataModule
from .data.bop.reader import Instance, read_depth
from .diffusion import Sampler
from .evaluate import SampledBatches
from .metrics import bop, bop19
from .module import PoseDiffusionModule

ROT_THRESHOLDS_DEG = (2.0, 5.0, 10.0)
TRANS_THRESHOLDS_CM = (2.0, 5.0, 10.0)


@torch.no_grad()
def predict_targets(
    module: PoseDiffusionModule,
    datamodule: BopDataModule,
    *,
    num_samples: int = 1,
    num_steps: int | None = None,
    sampler: Sampler | None = None,
    seed: int = 0,
    max_inputs: int | None = None,
) -> tuple[dict[tuple[int, int, int], dict[str, Any]], dict[str, Any]]:
    """The estimate for each test target the data module keeps: ``{(scene, im, gt_idx): {R, t, seconds}}``
    (camera frame, mm), and the run's timing and sampler fields (:meth:`SampledBatches.summary`)."""
    was_training = module.training
    module.eval()
    enc, out = datamodule.encoding, datamodule.image_size
    estimates: dict[tuple[int, int, int], dict[str, Any]] = {}
    run = SampledBatches(
        module, datamodule.test_dataloader(), num_samples, num_steps, sampler, seed, max_inputs
    )
    try:
        before = 0.0
        for batch, x in run:
            dt, before = run.seconds - before, run.seconds
            n = int(x.shape[0])
            x = x[:, 0].double().cpu()  # the first hypothesis is the estimate
            b = {k: batch[k].double().cpu() for k in ("K", "centre", "side", "translation")}
            # a rotation-only model is decoded (and scored) at the true translation
            R, t = enc.decode_pose(x, b["K"], b["centre"], b["side"], out, translation=b["translation"])
            for k in range(n):
                key = (int(batch["scene_id"][k]), int(batch["im_id"][k]), int(batch["gt_idx"][k]))
                estimates[key] = {"R": R[k].numpy(), "t": t[k].numpy(), "seconds": dt / n}
    finally:
        module.train(was_training)
    return estimates, run.summary()


class _Depths:
    """Renders model depth maps for VSD, one renderer per image size (made on first use)."""

    def __init__(self, datamodule: BopDataModule) -> None:
        self.dm = datamodule
        self.renderers: dict[tuple[int, int], Any] = {}

    def __call__(self, inst: Instance, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        from .data.bop.render import BopRenderer

        H, W = inst.image_hw
        r = self.renderers.get((H, W))
        if r is None:
            r = self.renderers[(H, W)] = BopRenderer(W, H)
        if inst.obj_id not in r.obj_ids:
            r.add_model(inst.obj_id, self.dm.models.mesh(inst.obj_id, True))
        return r.render_depth(inst.obj_id, R, t, inst.K)

    def close(self) -> None:
        for r in self.renderers.values():
            r.close()


def target_errors(
    datamodule: BopDataModule,
    estimates: dict[tuple[int, int, int], dict[str, Any]],
    targets: Sequence[Instance] | None = None,
    *,
    vsd: bool = True,
    vsd_delta: float = bop19.BOP19.vsd_delta,
) -> list[dict[str, Any]]:
    """One record per target (``targets``, default ``datamodule.targets``): its errors, NaN where
    there is no estimate."""
    depths = _Depths(datamodule) if vsd else None
    nan_vsd = [math.nan] * len(bop19.BOP19.vsd_taus)
    records = []
    try:
        for inst in datamodule.targets if targets is None else targets:
            est = estimates.get(inst.key)
            rec: dict[str, Any] = {"instance": inst, "estimated": est is not None}
            models = datamodule.models
            d = models.diameter(inst.obj_id, evaluation=True)
            if est is None:
                rec.update(mssd=math.nan, mspd=math.nan, vsd=nan_vsd, R=None, t=None)
                records.append(rec)
                continue
            pts, syms = models.points(inst.obj_id), models.symmetries(inst.obj_id, evaluation=True)
            R, t = est["R"], est["t"]
            rec.update(R=R, t=t, seconds=est["seconds"])
            rec["mssd"] = bop.mssd(R, t, inst.R, inst.t, pts, syms, diameter=d)
            rec["mspd"] = bop.mspd(R, t, inst.R, inst.t, inst.K, pts, syms)
            if depths is None:
                rec["vsd"] = nan_vsd
            elif not bop.sphere_projections_overlap(0.5 * d, t, inst.t):
                rec["vsd"] = [1.0] * len(bop19.BOP19.vsd_taus)
            else:
                rec["vsd"] = bop.vsd(
                    depths(inst, R, t),
                    depths(inst, inst.R, inst.t),
                    read_depth(inst.depth_path, inst.depth_scale),
                    inst.K,
                    vsd_delta,
                    bop19.BOP19.vsd_taus,
                    d,
                )
            records.append(rec)
    finally:
        if depths is not None:
            depths.close()
    return records


def _recalls(
    records: Sequence[dict[str, Any]], datamodule: BopDataModule, with_vsd: bool = True
) -> dict[str, float]:
    """The metrics of a set of target records (module docstring); without VSD, ``AR_VSD`` and ``AR``
    are NaN. MSPD is normalised by each target's own image width (the toolkit's 640 / w)."""
    n = len(records)
    if n == 0:
        return {}
    models = datamodule.models
    width = np.array([r["instance"].image_hw[1] for r in records], dtype=np.float64)
    ar = bop19.ar_from_paired_errors(
        vsd=np.array([r["vsd"] for r in records], dtype=np.float64) if with_vsd else None,
        mssd=np.array([r["mssd"] for r in records], dtype=np.float64),
        mspd=np.array([r["mspd"] for r in records], dtype=np.float64) * (REFERENCE_WIDTH / width),
        diameters=np.array([models.diameter(r["instance"].obj_id, evaluation=True) for r in records]),
        image_width=REFERENCE_WIDTH,
    )
    row: dict[str, float] = {"targets": float(n)}
    for key in ("AR_MSPD", "AR_MSSD", "AR_VSD", "AR"):
        row[key] = float(ar[key])
    est = [r for r in records if r["estimated"]]
    rec: dict[str, float] = {}
    if est:
        insts = [r["instance"] for r in est]
        rec = bop19.pose_recalls(
            np.stack([r["R"] for r in est]),
            np.stack([r["t"] for r in est]),
            np.stack([i.R for i in insts]),
            np.stack([i.t for i in insts]),
            [models.symmetries(i.obj_id, evaluation=True) for i in insts],
            rot_thresholds_deg=ROT_THRESHOLDS_DEG,
            trans_thresholds_mm=tuple(10.0 * c for c in TRANS_THRESHOLDS_CM),
        )
    frac = len(est) / n  # pose_recalls counts over the estimated targets; misses count as wrong
    for name in RECALL_NAMES:
        row[_KEYS[name[0]] + name[1:]] = float(rec.get(name, 0.0)) * frac
    return row


REFERENCE_WIDTH = 640.0
#: the names ``pose_recalls`` returns for the thresholds used here
RECALL_NAMES = (
    *(f"R@{d:g}" for d in ROT_THRESHOLDS_DEG),
    *(f"{a}@{c:g}cm" for a in "Txyz" for c in TRANS_THRESHOLDS_CM),
)
#: ``pose_recalls``' names → the report's metric keys (``R@2`` → ``recall_rot@2``, ``x@2cm`` → ``recall_x@2cm``)
_KEYS = {"R": "recall_rot", "T": "recall_trans", "x": "recall_x", "y": "recall_y", "z": "recall_z"}


def evaluate_bop(
    module: PoseDiffusionModule,
    datamodule: BopDataModule,
    *,
    num_samples: int = 1,
    num_steps: int | None = None,
    sampler: Sampler | None = None,
    seed: int = 0,
    max_inputs: int | None = None,
    vsd: bool = True,
) -> dict[str, Any]:
    """Per-object and overall BOP19 / paper metrics (module docstring), the estimates as BOP19 CSV
    rows (``estimates``), and timing. ``max_inputs`` scores only the targets predicted."""
    estimates, timing = predict_targets(
        module,
        datamodule,
        num_samples=num_samples,
        num_steps=num_steps,
        sampler=sampler,
        seed=seed,
        max_inputs=max_inputs,
    )
    targets = datamodule.targets
    if max_inputs is not None:  # a partial run scores the targets up to the last one predicted
        last = max((k for k, i in enumerate(targets) if i.key in estimates), default=-1)
        targets = targets[: last + 1]
    records = target_errors(datamodule, estimates, targets, vsd=vsd)
    result: dict[str, Any] = {"kind": "bop", "shapes": {}}
    by_obj: dict[int, list[dict[str, Any]]] = {}
    for r in records:
        by_obj.setdefault(r["instance"].obj_id, []).append(r)
    for obj_id in sorted(by_obj):
        result["shapes"][f"obj_{obj_id:06d}"] = _recalls(by_obj[obj_id], datamodule, vsd)
    result["overall"] = _recalls(records, datamodule, vsd)
    # the paper's "Avg(30)": every object counts once, whatever its number of targets
    keys = [k for k in result["overall"] if k != "targets"]
    rows = list(result["shapes"].values())
    result["object_mean"] = {k: float(np.nanmean([r[k] for r in rows])) if rows else math.nan for k in keys}
    per_image: dict[tuple[int, int], float] = {}
    for r in records:
        if r["estimated"]:
            i = r["instance"]
            per_image[(i.scene_id, i.im_id)] = per_image.get((i.scene_id, i.im_id), 0.0) + r["seconds"]
    result["estimates"] = [
        {
            "scene_id": r["instance"].scene_id,
            "im_id": r["instance"].im_id,
            "obj_id": r["instance"].obj_id,
            "score": 1.0,
            "R": np.asarray(r["R"]).reshape(3, 3).tolist(),
            "t": np.asarray(r["t"]).reshape(3).tolist(),
            "time": per_image[(r["instance"].scene_id, r["instance"].im_id)],
        }
        for r in records
        if r["estimated"]
    ]
    result.update(targets=len(records), skipped=sum(1 for r in records if not r["estimated"]), **timing)
    result["vsd"] = bool(vsd)
    return result


__all__ = ["evaluate_bop", "predict_targets", "target_errors"]
