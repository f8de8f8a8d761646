"""Evaluate a pose model on a BOP dataset — or score any BOP19 results — with the BOP19 protocol and
the paper's extra metrics, in-process.

**Estimates.** For every test target the data module keeps (BOP19 targets: the ``inst_count`` most
visible instances of each target object, cropped from the ground-truth box and masked to the
ground-truth visible pixels, as the paper), the model samples ``num_samples`` poses, decoded to the
camera frame (mm). One estimate per crop goes into the BOP19 results (:func:`estimates_of_predictions`):
with one hypothesis, that hypothesis with score 1 (the authors' evaluation); with several, the
heaviest of their modes (:func:`posediff.diffusion.modes`, 10° and 20 mm radii, in the camera
frame) with its weight — the fraction of the hypotheses it holds — as the score. These rows are
exactly what :func:`posediff.metrics.bop19.write_bop19_csv` writes and what is scored.

**Scoring** (:func:`score_estimates`, shared by ``posediff eval`` and ``posediff score``): the BOP19
protocol as the toolkit's ``eval_bop19_pose.py``. Per test image and object, the ``inst_count``
estimates with the highest scores (ties: file order) are each compared with EVERY target instance
of that object in that image (full error matrices); then, per threshold, they are matched greedily
in decreasing score to the unmatched instance with the smallest error below the threshold
(:func:`posediff.metrics.bop19.match`). So an estimate that lands on a sibling instance counts for
the sibling, and duplicates of one pose match one instance only. Errors: MSSD, MSPD
(:mod:`posediff.metrics.bop`) over the object's symmetry set and VSD (depth of the model at the
estimated and at the true pose rendered with :class:`posediff.data.bop.render.BopRenderer`, the
toolkit's camera convention; the test depth image read from disk; all errors 1 when the
bounding-sphere projections do not overlap), then the average recalls ``AR_MSPD``, ``AR_MSSD``,
``AR_VSD``, ``AR`` over all targets (:func:`posediff.metrics.bop19.average_recall`).

The paper's Table 3 recalls — symmetry-aware rotation error ``R@2/5/10°``, translation
``T@2/5/10 cm`` (smallest over the symmetries, the authors' ``teS``) and per axis
``x/y/z@2/5/10 cm`` — are per target: the top-``inst_count`` estimates are paired one-to-one with the targets, closest
pairs in MSSD first (the nearest whole pose; :func:`_paper_hits`), and a target is correct at a
threshold when its paired estimate's error is below it. (Matching each component by itself would let an estimate 3 cm off in x count for a
sibling that happens to share its x.) With one instance per object and image this is the authors'
paired evaluation.

Targets without any estimate (the data module dropped their crop: no or too few visible pixels, or
a results file left them out) count as misses. Rows of the result: per object (``obj_000001`` …),
``overall`` (recall over all targets, as the toolkit) and ``object_mean`` (the mean of the object
rows, the paper's "Avg(30)").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import torch

from ..data.bop.datamodule import BopDataModule
from ..data.bop.reader import Instance, read_depth
from ..diffusion import Sampler
from ..metrics import bop, bop19
from ..metrics.bop19 import BopEstimate
from ..models import PoseModule
from .sampling import SampledBatches
from .shapes import _fmt_thr as _label
from .shapes import _nanmean

ROT_THRESHOLDS_DEG = (2.0, 5.0, 10.0)
TRANS_THRESHOLDS_CM = (2.0, 5.0, 10.0)
#: mode radii for choosing the estimate among several hypotheses (degrees, mm)
MODE_RADIUS_DEG = 10.0
MODE_TRANSLATION_RADIUS_MM = 20.0
#: one image and object: ``(scene_id, im_id, obj_id)``
Key = tuple[int, int, int]


def best_hypothesis(R: torch.Tensor, t: torch.Tensor) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R (3, 3), t (3,), score)`` of one target's hypotheses ``R (S, 3, 3)``, ``t (S, 3)`` (mm):
    the hypothesis itself with score 1 when ``S = 1``; else the heaviest mode's pose and its weight."""
    if R.shape[0] == 1:
        return R[0].numpy(), t[0].numpy(), 1.0
    from ..diffusion import modes
    from ..lie import get_group

    x = torch.zeros((R.shape[0], 4, 4), dtype=torch.float64)
    x[:, :3, :3], x[:, :3, 3], x[:, 3, 3] = R.double(), t.double(), 1.0
    m = modes(
        x, get_group("r3so3"), radius_deg=MODE_RADIUS_DEG, translation_radius=MODE_TRANSLATION_RADIUS_MM
    )
    pose = m.poses[0]
    return pose[:3, :3].numpy(), pose[:3, 3].numpy(), float(m.weights[0])


@torch.no_grad()
def predict_targets(
    module: PoseModule,
    datamodule: BopDataModule,
    *,
    num_samples: int = 1,
    num_steps: int | None = None,
    sampler: Sampler | None = None,
    seed: int = 0,
    max_inputs: int | None = None,
) -> tuple[dict[tuple[int, int, int], dict[str, Any]], dict[str, Any]]:
    """The estimate for each test target the data module keeps: ``{(scene, im, gt_idx): {R, t, score,
    seconds}}`` (camera frame, mm; :func:`best_hypothesis`), and the run's timing and sampler fields
    (:meth:`SampledBatches.summary`)."""
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
            n, S = int(x.shape[0]), int(x.shape[1])
            x = x.double().cpu()
            b = {k: batch[k].double().cpu() for k in ("K", "centre", "side", "translation")}
            # a rotation-only model is decoded (and scored) at the true translation
            R, t = enc.decode_pose(
                x, b["K"][:, None], b["centre"][:, None], b["side"][:, None], out,
                translation=b["translation"][:, None].expand(n, S, 3),
            )  # fmt: skip
            for k in range(n):
                key = (int(batch["scene_id"][k]), int(batch["im_id"][k]), int(batch["gt_idx"][k]))
                Rk, tk, score = best_hypothesis(R[k], t[k])
                estimates[key] = {"R": Rk, "t": tk, "score": score, "seconds": dt / n}
    finally:
        module.train(was_training)
    return estimates, run.summary()


def estimates_of_predictions(
    datamodule: BopDataModule, predictions: dict[tuple[int, int, int], dict[str, Any]]
) -> list[BopEstimate]:
    """The BOP19 rows of :func:`predict_targets`' estimates, in target order; ``time`` is the seconds
    spent on the whole image (the sum over its targets' crops, as BOP19 asks)."""
    by_key = {i.key: i for i in datamodule.targets}
    per_image: dict[tuple[int, int], float] = {}
    for key, est in predictions.items():
        per_image[key[:2]] = per_image.get(key[:2], 0.0) + float(est["seconds"])
    rows = []
    for inst in datamodule.targets:
        est = predictions.get(inst.key)
        if est is None:
            continue
        rows.append(
            BopEstimate(
                inst.scene_id,
                inst.im_id,
                inst.obj_id,
                float(est.get("score", 1.0)),
                np.asarray(est["R"]),
                np.asarray(est["t"]),
                per_image[inst.key[:2]],
            )  # fmt: skip
        )
    missing = set(predictions) - set(by_key)
    if missing:
        raise ValueError(f"estimates for instances that are no targets: {sorted(missing)[:3]}")
    return rows


def check_estimates(
    estimates: Sequence[BopEstimate], datamodule: BopDataModule, where: Sequence[str] | None = None
) -> None:
    """Refuse, with one line naming the row (:class:`~posediff.metrics.bop19.BopResultsError`), an
    estimate whose ``R`` is no rotation (orthonormal with det +1 within
    :data:`~posediff.metrics.bop19.ROTATION_TOLERANCE`: a scaled R, a reflection or zeros would
    otherwise be scored — a scaled R keeps its rotation angle), of an object the dataset's models do
    not have or of an image that holds no target. ``where``: how to name each row (default: the
    row's own ``where``, ``path:line`` when read by :func:`~posediff.metrics.bop19.read_bop19_csv`,
    else ``row N``). An estimate of an object that is no target of its image is not refused: the
    toolkit ignores it, and so does :func:`score_estimates` (``estimates_ignored``)."""
    images = {i.key[:2] for i in datamodule.targets}
    known = set(datamodule.models.obj_ids)
    for k, e in enumerate(estimates):
        name = where[k] if where is not None else (e.where or f"row {k + 1}")
        bop19.check_rotation(e.R, name)
        if e.obj_id not in known:
            ids = ", ".join(str(o) for o in sorted(known))
            raise bop19.BopResultsError(
                f"{name}: obj_id {e.obj_id} is not in {datamodule.models.info_path} (objects {ids})"
            )
        if (e.scene_id, e.im_id) not in images:
            raise bop19.BopResultsError(
                f"{name}: scene {e.scene_id} image {e.im_id} holds no target of "
                f"{datamodule.root / (datamodule.targets_file or datamodule.test_split)}"
            )


def read_results_file(csv: Any) -> list[BopEstimate]:
    """The estimates of a BOP19 results CSV (any method's); a missing or empty file refused in one line."""
    from pathlib import Path

    csv = Path(str(csv))
    if not csv.is_file():
        raise FileNotFoundError(
            f"csv={csv}: no such file (a BOP19 results CSV: scene_id,im_id,obj_id,score,R,t,time)"
        )
    rows = bop19.read_bop19_csv(csv)
    if not rows:
        raise ValueError(f"{csv}: no estimates in the file")
    return rows


def scoring_setup(
    rows: Sequence[BopEstimate],
    datamodule: Any,
    vsd_delta: float | None = None,
    *,
    data_name: str | None = None,
) -> float:
    """Make ``datamodule`` (a BOP data module; anything else refused) ready to score ``rows``: its test
    targets read, the rows checked against them (:func:`check_estimates`). Returns the VSD tolerance
    in mm: ``vsd_delta``, else the dataset's own (:data:`~posediff.metrics.bop19.VSD_DELTAS`, by its
    folder name; 15 mm otherwise). ``data_name``: how a refusal names the data (its config's
    ``_target_``). Bad input: one-line ``ValueError``."""
    if not isinstance(datamodule, BopDataModule):
        name = data_name or f"{type(datamodule).__module__}.{type(datamodule).__qualname__}"
        raise ValueError(f"data={name} is not a BOP dataset; posediff score needs one (data=tless)")
    datamodule.read_targets()
    check_estimates(rows, datamodule)
    if vsd_delta is None:
        name = datamodule.root.name.lower().replace("_", "").replace("-", "")
        vsd_delta = bop19.VSD_DELTAS.get(name, 15.0)
    if not float(vsd_delta) > 0:
        raise ValueError(f"vsd_delta must be > 0 mm, got {vsd_delta}")
    return float(vsd_delta)


class _Depths:
    """Depth maps for VSD: renders of a model at a pose (one renderer per image size, made on first
    use), the ground truth's cached per instance, and the test depth images (the last one read)."""

    def __init__(self, datamodule: BopDataModule) -> None:
        self.dm = datamodule
        self.renderers: dict[tuple[int, int], Any] = {}
        self.gt: dict[tuple[int, int, int], np.ndarray] = {}
        self.test_key: tuple[int, int] | None = None
        self.test_depth: np.ndarray | None = None

    def render(self, inst: Instance, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        from ..data.bop.render import BopRenderer

        H, W = inst.image_hw
        r = self.renderers.get((H, W))
        if r is None:
            r = self.renderers[(H, W)] = BopRenderer(W, H)
        if inst.obj_id not in r.obj_ids:
            r.add_model(inst.obj_id, self.dm.models.mesh(inst.obj_id, True))
        return r.render_depth(inst.obj_id, R, t, inst.K)

    def truth(self, inst: Instance) -> np.ndarray:
        if inst.key not in self.gt:
            self.gt = {k: v for k, v in self.gt.items() if k[:2] == inst.key[:2]}  # this image's only
            self.gt[inst.key] = self.render(inst, inst.R, inst.t)
        return self.gt[inst.key]

    def test(self, inst: Instance) -> np.ndarray:
        if self.test_key != inst.key[:2] or self.test_depth is None:
            self.test_depth = read_depth(inst.depth_path, inst.depth_scale)
            self.test_key = inst.key[:2]
        return self.test_depth

    def close(self) -> None:
        for r in self.renderers.values():
            r.close()


#: the paper's recalls: (name, error, thresholds); errors in degrees or mm
def _paper_thresholds() -> list[tuple[str, np.ndarray]]:
    mm = np.asarray(TRANS_THRESHOLDS_CM) * 10.0
    out = [("rot", np.asarray(ROT_THRESHOLDS_DEG)), ("trans", mm)]
    return out + [(axis, mm) for axis in "xyz"]


def _paper_keys() -> list[str]:
    keys = [f"recall_rot@{_label(d)}" for d in ROT_THRESHOLDS_DEG]
    for name in ("trans", "x", "y", "z"):
        keys += [f"recall_{name}@{_label(c)}cm" for c in TRANS_THRESHOLDS_CM]
    return keys


def _paper_hits(err: dict[str, np.ndarray], paper: list[tuple[str, np.ndarray]]) -> np.ndarray:
    """``(G, n_keys)`` bool: the paper's recalls of one image and object's targets. The (top-``inst_count``)
    estimates are first paired one-to-one with targets, closest pairs first: repeatedly the unpaired
    (estimate, target) pair with the smallest MSSD (where MSSD is infinite — centres a diameter or
    more apart — the nearest translation; ties in order). Every component error (rotation, one axis)
    is then measured against the instance the whole pose is nearest to, never against a sibling that
    happens to agree in that component only."""
    E, G = err["mssd"].shape
    cost = np.where(np.isfinite(err["mssd"]), err["mssd"], 1e12 + err["trans"])
    pair = np.full(E, -1)
    used_e, used_g = np.zeros(E, dtype=bool), np.zeros(G, dtype=bool)
    for flat in np.argsort(cost, axis=None, kind="stable"):
        i, j = divmod(int(flat), G)
        if not used_e[i] and not used_g[j]:
            pair[i], used_e[i], used_g[j] = j, True, True
    out = []
    for name, th in paper:
        hit = np.zeros((G, len(th)), dtype=bool)
        for i, j in enumerate(pair):
            if j >= 0:
                hit[j] = err[name][i, j] < th
        out.append(hit)
    return np.concatenate(out, axis=1)


def _pair_errors(
    datamodule: BopDataModule,
    ests: Sequence[BopEstimate],
    gts: Sequence[Instance],
    depths: _Depths | None,
    vsd_delta: float,
    protocol: bop19.Bop19Protocol,
) -> dict[str, np.ndarray]:
    """The errors of every estimate (E) against every target instance (G) of one object in one image:
    ``mssd``, ``mspd`` (E, G); ``vsd`` (E, G, n_τ) when ``depths``; the paper's ``rot`` (degrees),
    ``trans``, ``x``, ``y``, ``z`` (mm) (E, G)."""
    E, G = len(ests), len(gts)
    obj_id = gts[0].obj_id
    models = datamodule.models
    d = models.diameter(obj_id, evaluation=True)
    n_tau = len(protocol.vsd_taus)
    out: dict[str, np.ndarray] = {}
    if E == 0:
        for name in ("mssd", "mspd", "rot", "trans", "x", "y", "z"):
            out[name] = np.zeros((0, G))
        if depths is not None:
            out["vsd"] = np.zeros((0, G, n_tau))
        return out
    pts, syms = models.points(obj_id), models.symmetry_set(obj_id, evaluation=True)
    Re = np.repeat(np.stack([e.R for e in ests]), G, axis=0)  # pair (e, g) at row e·G + g
    te = np.repeat(np.stack([e.t for e in ests]), G, axis=0)
    Rg = np.tile(np.stack([g.R for g in gts]), (E, 1, 1))
    tg = np.tile(np.stack([g.t for g in gts]), (E, 1))
    K = np.tile(np.stack([g.K for g in gts]), (E, 1, 1))
    out["mssd"] = np.asarray(bop.mssd(Re, te, Rg, tg, pts, syms, diameter=d)).reshape(E, G)
    out["mspd"] = np.asarray(bop.mspd(Re, te, Rg, tg, K, pts, syms)).reshape(E, G)
    out["rot"] = bop19.symmetric_rotation_errors_deg(Re, Rg, syms).reshape(E, G)
    deltas = bop19.symmetric_translation_deltas(te, Rg, tg, syms)  # (E·G, S, 3)
    out["trans"] = np.linalg.norm(deltas, axis=-1).min(axis=1).reshape(E, G)
    for k, axis in enumerate("xyz"):
        out[axis] = np.abs(deltas[..., k]).min(axis=1).reshape(E, G)
    if depths is not None:
        v = np.ones((E, G, n_tau))
        for i, e in enumerate(ests):
            rendered = None
            for j, g in enumerate(gts):
                if not bop.sphere_projections_overlap(0.5 * d, e.t, g.t):
                    continue  # the toolkit's short-cut: every error 1
                if rendered is None:
                    rendered = depths.render(g, e.R, e.t)
                v[i, j] = bop.vsd(
                    rendered, depths.truth(g), depths.test(g), g.K, vsd_delta, protocol.vsd_taus, d
                )
        out["vsd"] = v
    return out


def score_estimates(
    datamodule: BopDataModule,
    estimates: Iterable[BopEstimate],
    targets: Sequence[Instance] | None = None,
    *,
    vsd: bool = True,
    vsd_delta: float = bop19.BOP19.vsd_delta,
    protocol: bop19.Bop19Protocol = bop19.BOP19,
) -> dict[str, Any]:
    """BOP19 scores (module docstring) of ``estimates`` on the data module's test targets (``targets``,
    default :attr:`BopDataModule.targets`, e.g. a prefix for a partial run): rows ``shapes``
    (per object), ``overall``, ``object_mean``, and the counts ``targets`` (instances scored),
    ``estimates_scored`` (the top-``inst_count`` rows per image and object of a target),
    ``estimates_ignored`` (the rest: beyond ``inst_count``, or of an image / object that is no target).
    Without ``vsd``, ``AR_VSD`` and ``AR`` are NaN."""
    targets = list(datamodule.targets if targets is None else targets)
    groups: dict[Key, list[Instance]] = {}
    for inst in targets:
        groups.setdefault((inst.scene_id, inst.im_id, inst.obj_id), []).append(inst)
    by_group: dict[Key, list[BopEstimate]] = {}
    total = 0
    for e in estimates:
        total += 1
        by_group.setdefault((e.scene_id, e.im_id, e.obj_id), []).append(e)
    paper = _paper_thresholds()
    names = ["mssd", "mspd", *(["vsd"] if vsd else [])]
    bop_groups: list[bop19.ImageObjectErrors] = []
    paper_hits: list[np.ndarray] = []  # per target: (n_keys,) bool
    obj_of_target: list[int] = []
    scored = 0
    depths = _Depths(datamodule) if vsd else None
    try:
        for key, gts in groups.items():
            top = datamodule.inst_count.get(key, len(gts))
            ests = by_group.get(key, [])
            order = sorted(range(len(ests)), key=lambda i: -ests[i].score)[:top]  # stable: file order on ties
            ests = [ests[i] for i in order]
            scored += len(ests)
            err = _pair_errors(datamodule, ests, gts, depths, vsd_delta, protocol)
            scores = np.array([e.score for e in ests], dtype=np.float64)
            bop_groups.append(
                bop19.ImageObjectErrors(
                    obj_id=key[2],
                    diameter=datamodule.models.diameter(key[2], evaluation=True),
                    image_width=float(gts[0].image_hw[1]),
                    scores=scores,
                    visib_fract=np.ones(len(gts)),  # every instance given is a target
                    inst_count=len(ests),
                    scene_id=key[0],
                    im_id=key[1],
                    **{n: err[n] for n in names},
                )
            )
            paper_hits.append(_paper_hits(err, paper))
            obj_of_target += [key[2]] * len(gts)
    finally:
        if depths is not None:
            depths.close()
    ar = bop19.average_recall(bop_groups, protocol)
    hits_all = np.concatenate(paper_hits) if paper_hits else np.zeros((0, len(_paper_keys())), dtype=bool)
    obj_ids = np.asarray(obj_of_target, dtype=np.int64)
    keys = _paper_keys()

    def row(ar_part: dict[str, Any], mask: np.ndarray) -> dict[str, float]:
        n = int(mask.sum())
        r: dict[str, float] = {"targets": float(n)}
        for k in ("AR_MSPD", "AR_MSSD", "AR_VSD", "AR"):
            r[k] = float(ar_part[k])  # AR_VSD and AR are NaN without VSD
        rec = hits_all[mask].mean(axis=0) if n else np.zeros(len(keys))
        r.update({k: float(v) for k, v in zip(keys, rec, strict=True)})
        return r

    result: dict[str, Any] = {"kind": "bop", "matching": "bop19", "shapes": {}}
    for o in sorted(ar["per_object"]):
        result["shapes"][f"obj_{o:06d}"] = row(ar["per_object"][o], obj_ids == o)
    result["overall"] = row(ar, np.ones(len(obj_ids), dtype=bool)) if len(obj_ids) else {}
    rows = list(result["shapes"].values())
    mean_keys = [k for k in result["overall"] if k != "targets"]
    result["object_mean"] = {k: _nanmean([r[k] for r in rows]) for k in mean_keys}
    result.update(
        targets=len(targets),
        without_estimate=sum(len(g) for k, g in groups.items() if k not in by_group),
        estimates_scored=scored,
        estimates_ignored=total - scored,
        vsd=bool(vsd),
    )
    return result


def evaluate_bop(
    module: PoseModule,
    datamodule: BopDataModule,
    *,
    num_samples: int = 1,
    num_steps: int | None = None,
    sampler: Sampler | None = None,
    seed: int = 0,
    max_inputs: int | None = None,
    vsd: bool = True,
) -> dict[str, Any]:
    """Per-object and overall BOP19 / paper metrics of a model (module docstring), the estimates as
    BOP19 rows (``estimates``: exactly the rows scored), and timing. ``max_inputs`` scores only the
    targets up to the last one predicted."""
    predictions, timing = predict_targets(
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
        last = max((k for k, i in enumerate(targets) if i.key in predictions), default=-1)
        targets = targets[: last + 1]
    rows = estimates_of_predictions(datamodule, predictions)
    result = score_estimates(datamodule, rows, targets, vsd=vsd)
    skipped = set(datamodule.skipped)
    result["skipped"] = sum(1 for i in targets if i in skipped)
    result["estimates"] = [
        {"scene_id": e.scene_id, "im_id": e.im_id, "obj_id": e.obj_id, "score": e.score,
         "R": e.R.tolist(), "t": e.t.tolist(), "time": e.time}
        for e in rows
    ]  # fmt: skip
    result.update(**timing)
    return result


__all__ = [
    "best_hypothesis",
    "check_estimates",
    "estimates_of_predictions",
    "evaluate_bop",
    "predict_targets",
    "read_results_file",
    "score_estimates",
    "scoring_setup",
]
