"""The BOP19 evaluation protocol (Hodaň et al., "BOP Challenge 2020 on 6D Object Localization",
ECCVW 2020; as the BOP toolkit's ``eval_bop19_pose.py`` defines it), on errors from
:mod:`posediff.metrics.bop`, plus the paper's pose recalls and the BOP19 results CSV.

**Thresholds** (:data:`BOP19`). An estimate is correct w.r.t. a ground truth iff its error is
STRICTLY below the threshold:

* VSD (τ = 0.05, 0.10, …, 0.50 of the diameter, δ = 15 mm, 5 mm for ITODD): correct iff
  ``e_VSD(τ) < θ`` with θ = 0.05, …, 0.50 — 10 τ × 10 θ = 100 recalls.
* MSSD: correct iff ``e_MSSD / diameter < k`` with k = 0.05, …, 0.50 — 10 recalls.
* MSPD: correct iff ``e_MSPD · 640 / w < k`` with k = 5, 10, …, 50 px and w the image width in pixels
  — the pixel threshold is ``k · w / 640`` (5.625 px at k = 5 for w = 720), i.e. the error is
  normalised to a 640-pixel-wide image — 10 recalls.

**Targets.** A ground-truth (GT) instance is a target iff ``visib_fract ≥ 0.1``. Other instances are
ignored: they are not counted, and cannot be matched (so an estimate landing on one is neither a hit
nor penalised — recall has no false-positive term anyway).

**Matching** (:func:`match`), separately for each threshold (each (τ, θ) pair for VSD) and each
(scene, image, object): only the ``inst_count`` estimates with the highest scores are considered
(``inst_count`` = the number of targets of that object in that image); in decreasing score (ties
keep the input order), each estimate is matched to the not-yet-matched target with the smallest
error among those whose error is below the threshold (ties: the first such target).

**Recall** for one threshold = matched targets / all targets of the dataset (a target without any
estimate is a miss); ``AR_VSD``, ``AR_MSSD``, ``AR_MSPD`` = the mean of their recalls (100, 10, 10),
``AR`` = their mean. The toolkit pools all targets of the dataset into ONE recall per threshold
(a micro-average: objects with many targets weigh more), it does not average per-object recalls;
the per-object recalls (and their plain mean, ``AR_obj_mean``) are reported next to it but are no part
of the BOP score. With no target at all a recall is 0 (as the toolkit's).

**Full error matrices** (:func:`average_recall`): every estimate of an image and object against every
target instance of that object in that image, then the matching above — the toolkit's scores; this
is what ``posediff eval`` and ``posediff score`` use (:func:`posediff.evaluation.bop.score_estimates`).
**Paired errors** (:func:`ar_from_paired_errors`): each target with at most one estimate scored
against its own GT only — the toolkit's result only with one instance per object and image; with
sibling instances an estimate could also match a sibling, which pairing cannot see.

Units: translations and distances in mm (BOP), MSPD in pixels, angles in degrees.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._io import atomic_write_text
from ..symmetry import SymmetrySet, min_angle_deg
from ._arrays import as_float64 as _np


def _steps(step: float, n: int = 10) -> tuple[float, ...]:
    return tuple(round(step * k, 10) for k in range(1, n + 1))


@dataclass(frozen=True)
class Bop19Protocol:
    """The BOP19 thresholds (module docstring). The toolkit builds them with ``np.arange``, whose values
    differ from these decimals in the last bits (e.g. 0.15000000000000002), which only matters for
    errors within ~1e-16 of a threshold."""

    vsd_taus: tuple[float, ...] = _steps(0.05)  # misalignment tolerance, fraction of the diameter
    vsd_thetas: tuple[float, ...] = _steps(0.05)  # correctness threshold on e_VSD
    vsd_delta: float = 15.0  # visibility tolerance, mm (T-LESS and most datasets; ITODD: 5)
    mssd_thresholds: tuple[float, ...] = _steps(0.05)  # fractions of the object diameter
    mspd_thresholds: tuple[float, ...] = _steps(5.0)  # px for a 640-pixel-wide image
    reference_width: float = 640.0
    visib_gt_min: float = 0.1  # minimum visible fraction of a target
    max_sym_disc_step: float = 0.01  # for posediff.metrics.bop.symmetry_transforms

    def mspd_thresholds_px(self, image_width: float) -> np.ndarray:
        """The MSPD thresholds in pixels of an image ``image_width`` wide: ``k · w / 640``."""
        return np.asarray(self.mspd_thresholds) * float(image_width) / self.reference_width


BOP19 = Bop19Protocol()

#: The toolkit's VSD δ per dataset (mm).
VSD_DELTAS: dict[str, float] = {
    **dict.fromkeys(
        ("hb", "icbin", "icmi", "lm", "lmo", "ruapc", "tless", "tudl", "tyol", "ycbv", "hope"), 15.0
    ),
    "itodd": 5.0,
}


# --------------------------------------------------------------------------------------------------
# Correctness per threshold
# --------------------------------------------------------------------------------------------------


def vsd_correct(vsd: Any, protocol: Bop19Protocol = BOP19) -> np.ndarray:
    """``vsd (…, n_τ)`` (errors for ``protocol.vsd_taus``) → ``(…, n_τ, n_θ)`` bool: ``e(τ) < θ``
    (NaN: not correct)."""
    e = _np(vsd)
    if e.shape[-1:] != (len(protocol.vsd_taus),):
        raise ValueError(f"vsd must end in {len(protocol.vsd_taus)} (one error per τ), got {e.shape}")
    return e[..., None] < np.asarray(protocol.vsd_thetas)


def mssd_correct(mssd: Any, diameter: Any, protocol: Bop19Protocol = BOP19) -> np.ndarray:
    """``mssd (…)``, ``diameter`` (broadcastable, same units) → ``(…, n_k)`` bool:
    ``mssd / diameter < k`` (the toolkit normalises the error; NaN: not correct)."""
    with np.errstate(invalid="ignore"):
        e = _np(mssd) / _np(diameter)
    return e[..., None] < np.asarray(protocol.mssd_thresholds)


def mspd_correct(mspd: Any, image_width: Any, protocol: Bop19Protocol = BOP19) -> np.ndarray:
    """``mspd (…)`` px, ``image_width`` (broadcastable) px → ``(…, n_k)`` bool:
    ``mspd · (640 / w) < k`` (the toolkit's normalisation; NaN: not correct)."""
    with np.errstate(invalid="ignore"):
        e = (protocol.reference_width / _np(image_width)) * _np(mspd)
    return e[..., None] < np.asarray(protocol.mspd_thresholds)


# --------------------------------------------------------------------------------------------------
# Matching
# --------------------------------------------------------------------------------------------------


class Matches(NamedTuple):
    """Result of :func:`match`, with ``T…`` the broadcast threshold shape."""

    gt_matched: np.ndarray  # (T…, G) bool: the GT instance has a matched estimate
    est_to_gt: np.ndarray  # (T…, E) int: the GT matched to each estimate, -1 for none


def match(
    scores: Any,
    errors: Any,
    thresholds: Any,
    *,
    gt_valid: Any = None,
    max_estimates: int | None = None,
) -> Matches:
    """The toolkit's greedy matching of the estimates of ONE object in ONE image to its GT instances.

    ``scores (E,)``; ``errors (E, G, …)`` — the error of each estimate w.r.t. each GT instance, in the
    units of ``thresholds``, optionally with trailing dimensions that broadcast against
    ``thresholds`` (e.g. ``(E, G)`` with ``(T,)``: the same errors at T thresholds; ``(E, G, T)`` with
    ``(T,)``: one error per threshold; VSD: ``(E, G, n_τ, 1)`` with ``θ (n_θ,)``). ``gt_valid (G,)``:
    the targets (default all; invalid ones are never matched). ``max_estimates``: only the top-k
    estimates by score take part (BOP19: ``inst_count``; None: all; 0: none).

    For each threshold independently, in decreasing score, an estimate is matched to the unmatched
    valid GT with the smallest error among those with ``error < threshold`` (strict), if any. NaN
    errors never match.
    """
    s = _np(scores).reshape(-1)
    err = _np(errors)
    E = len(s)
    if err.ndim < 2 or err.shape[0] != E:
        raise ValueError(f"errors must be (E={E}, G, …), got {err.shape}")
    G = err.shape[1]
    th = _np(thresholds)
    t_shape = np.broadcast_shapes(err.shape[2:], th.shape)
    T = math.prod(t_shape)
    extra = err.shape[2:]
    err = err.reshape(E, G, *(1,) * (len(t_shape) - len(extra)), *extra)  # right-aligned, as numpy
    e = np.broadcast_to(err, (E, G, *t_shape)).reshape(E, G, T)
    th = np.broadcast_to(th, t_shape).reshape(T)
    valid = np.ones(G, dtype=bool) if gt_valid is None else np.asarray(gt_valid, dtype=bool).reshape(G)
    order = np.argsort(-s, kind="stable")
    if max_estimates is not None:
        order = order[: max(0, int(max_estimates))]
    matched = np.zeros((T, G), dtype=bool)
    est_to_gt = np.full((T, E), -1, dtype=np.int64)
    rows = np.arange(T)
    with np.errstate(invalid="ignore"):
        below = e < th  # (E, G, T)
    for i in order:
        cand = below[i].T & ~matched & valid  # (T, G)
        best = np.where(cand, e[i].T, np.inf).argmin(axis=1)  # first of the smallest
        hit = cand[rows, best]
        matched[rows[hit], best[hit]] = True
        est_to_gt[rows[hit], i] = best[hit]
    return Matches(matched.reshape(*t_shape, G), est_to_gt.reshape(*t_shape, E))


# --------------------------------------------------------------------------------------------------
# Average recall
# --------------------------------------------------------------------------------------------------


def _recall(hits: np.ndarray, n: int) -> np.ndarray:
    return hits.sum(axis=0) / n if n else np.zeros(hits.shape[1:])


def _summary(
    hits: dict[str, np.ndarray | None], targets: np.ndarray, obj_ids: np.ndarray | None
) -> dict[str, Any]:
    """``hits[name] (M, …)`` bool per GT row; ``targets (M,)`` which rows count."""

    def scores(mask: np.ndarray) -> dict[str, Any]:
        n = int(mask.sum())
        out: dict[str, Any] = {"n_targets": n}
        for name in ("vsd", "mssd", "mspd"):
            h = hits[name]
            rec = None if h is None else _recall(h[mask], n)
            out[f"recall_{name}"] = rec
            out[f"AR_{name.upper()}"] = math.nan if rec is None else float(rec.mean())
        parts = [out["AR_VSD"], out["AR_MSSD"], out["AR_MSPD"]]
        out["AR"] = float(np.mean(parts))  # NaN unless all three are given
        return out

    result = scores(targets)
    if obj_ids is not None:
        per = {}
        for o in np.unique(obj_ids[targets]):
            sub = scores(targets & (obj_ids == o))
            per[int(o)] = {k: v for k, v in sub.items() if not k.startswith("recall_")}
        result["per_object"] = per
        result["AR_obj_mean"] = float(np.mean([v["AR"] for v in per.values()])) if per else math.nan
    return result


def ar_from_paired_errors(
    vsd: Any,
    mssd: Any,
    mspd: Any,
    diameters: Any,
    image_width: Any,
    *,
    obj_ids: Any = None,
    visib_fract: Any = None,
    protocol: Bop19Protocol = BOP19,
) -> dict[str, Any]:
    """BOP19 average recall when each target has (at most) one paired estimate.

    ``vsd (N, n_τ)`` (errors at ``protocol.vsd_taus``), ``mssd (N,)`` (units of ``diameters``),
    ``mspd (N,)`` px, ``diameters (N,)`` or scalar, ``image_width`` px, scalar or ``(N,)``; a missing
    estimate is NaN (never correct). Any of ``vsd`` / ``mssd`` / ``mspd`` may be None: its AR is NaN
    and so is ``AR``. ``visib_fract (N,)``: rows below ``protocol.visib_gt_min`` are not targets
    (default: all rows are). ``obj_ids (N,)``: adds ``per_object`` ({obj_id: {AR…, n_targets}}) and
    ``AR_obj_mean`` (their unweighted mean, not the BOP score).

    Returns ``AR``, ``AR_VSD``, ``AR_MSSD``, ``AR_MSPD``, ``recall_vsd (n_τ, n_θ)``,
    ``recall_mssd (n_k,)``, ``recall_mspd (n_k,)``, ``n_targets``. Recall pools all targets (module
    docstring)."""
    given = [a for a in (vsd, mssd, mspd) if a is not None]
    if not given:
        raise ValueError("give at least one of vsd, mssd, mspd")
    N = len(np.atleast_1d(_np(given[0])))
    hits: dict[str, np.ndarray | None] = {"vsd": None, "mssd": None, "mspd": None}
    if vsd is not None:
        v = _np(vsd)
        if v.shape != (N, len(protocol.vsd_taus)):
            raise ValueError(f"vsd must be (N={N}, {len(protocol.vsd_taus)}), got {v.shape}")
        hits["vsd"] = vsd_correct(v, protocol)
    if mssd is not None:
        hits["mssd"] = mssd_correct(_check_n(mssd, N, "mssd"), _per_row(diameters, N), protocol)
    if mspd is not None:
        hits["mspd"] = mspd_correct(_check_n(mspd, N, "mspd"), _per_row(image_width, N), protocol)
    targets = np.ones(N, dtype=bool)
    if visib_fract is not None:
        targets = _check_n(visib_fract, N, "visib_fract") >= protocol.visib_gt_min
    ids = None if obj_ids is None else np.asarray(obj_ids).reshape(-1)
    if ids is not None and len(ids) != N:
        raise ValueError(f"obj_ids must be ({N},), got {ids.shape}")
    return _summary(hits, targets, ids)


def _check_n(x: Any, N: int, name: str) -> np.ndarray:
    a = _np(x).reshape(-1)
    if len(a) != N:
        raise ValueError(f"{name} must be ({N},), got {np.shape(x)}")
    return a


def _per_row(x: Any, N: int) -> np.ndarray:
    a = _np(x).reshape(-1)
    if len(a) not in (1, N):
        raise ValueError(f"expected a scalar or ({N},), got {np.shape(x)}")
    return np.broadcast_to(a, (N,))


@dataclass
class ImageObjectErrors:
    """The estimates and GT instances of ONE object in ONE image, with all their pairwise errors (for
    :func:`average_recall`). ``scores (E,)``; ``visib_fract (G,)``; ``vsd (E, G, n_τ)``, ``mssd (E, G)``
    (units of ``diameter``), ``mspd (E, G)`` px — each optional, but given for all groups or none.
    ``inst_count``: how many top-scored estimates count (default: the number of targets,
    ``visib_fract ≥ visib_gt_min``, as in the toolkit's ``test_targets_bop19.json``)."""

    obj_id: int
    diameter: float
    image_width: float
    scores: Any
    visib_fract: Any
    vsd: Any = None
    mssd: Any = None
    mspd: Any = None
    inst_count: int | None = None
    scene_id: int = 0
    im_id: int = 0


def average_recall(groups: Iterable[ImageObjectErrors], protocol: Bop19Protocol = BOP19) -> dict[str, Any]:
    """BOP19 average recall over a dataset given as (scene, image, object) groups with full
    estimate × GT error matrices: per group the toolkit's matching (:func:`match`, top-``inst_count``
    estimates, targets = ``visib_fract ≥ 0.1``), then recall per threshold over all targets. Returns
    the keys of :func:`ar_from_paired_errors`, always with ``per_object``."""
    rows: dict[str, list[np.ndarray]] = defaultdict(list)
    targets, ids = [], []
    present: set[tuple[str, bool]] = set()
    taus, thetas = np.asarray(protocol.vsd_taus), np.asarray(protocol.vsd_thetas)
    for k, g in enumerate(groups):
        s = _np(g.scores).reshape(-1)
        vis = _np(g.visib_fract).reshape(-1)
        E, G = len(s), len(vis)
        valid = vis >= protocol.visib_gt_min
        top = int(valid.sum()) if g.inst_count is None else int(g.inst_count)
        for name in ("vsd", "mssd", "mspd"):
            present.add((name, getattr(g, name) is None))
        if g.vsd is not None:
            v = _np(g.vsd)
            if v.shape != (E, G, len(taus)):
                raise ValueError(f"group {k}: vsd must be ({E}, {G}, {len(taus)}), got {v.shape}")
            m = match(s, v[..., None], thetas, gt_valid=valid, max_estimates=top).gt_matched
            rows["vsd"].append(np.moveaxis(m, -1, 0))  # (G, n_τ, n_θ)
        for name, ths in (("mssd", protocol.mssd_thresholds), ("mspd", protocol.mspd_thresholds)):
            a = getattr(g, name)
            if a is None:
                continue
            a = _np(a)
            if a.shape != (E, G):
                raise ValueError(f"group {k}: {name} must be ({E}, {G}), got {a.shape}")
            # the toolkit's normalisation: MSSD / diameter, MSPD · 640 / w
            a = (
                a / float(g.diameter)
                if name == "mssd"
                else (protocol.reference_width / float(g.image_width)) * a
            )
            found = match(s, a, np.asarray(ths), gt_valid=valid, max_estimates=top)
            rows[name].append(found.gt_matched.T)  # (G, n_k)
        targets.append(valid)
        ids.append(np.full(G, g.obj_id))
    for name in ("vsd", "mssd", "mspd"):
        if (name, True) in present and (name, False) in present:
            raise ValueError(f"{name} errors are given for some groups but not for others")
    shapes = {
        "vsd": (len(protocol.vsd_taus), len(protocol.vsd_thetas)),
        "mssd": (len(protocol.mssd_thresholds),),
        "mspd": (len(protocol.mspd_thresholds),),
    }
    hits = {
        name: (np.concatenate(rows[name]) if rows[name] else np.zeros((0, *shape), dtype=bool))
        if (name, False) in present or not present
        else None
        for name, shape in shapes.items()
    }
    gt_targets = np.concatenate(targets) if targets else np.zeros(0, dtype=bool)
    gt_ids = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
    return _summary(hits, gt_targets, gt_ids)


# --------------------------------------------------------------------------------------------------
# The paper's pose recalls
# --------------------------------------------------------------------------------------------------


def _sym_rotations(syms: Any) -> np.ndarray:
    """``R_S (S, 3, 3)`` of one symmetry set: None (identity), a :class:`~posediff.symmetry.SymmetrySet`
    (discretised at BOP's 0.01), the ``(R_S, t_S)`` tuple of
    :func:`~posediff.metrics.bop.symmetry_transforms`, or the rotations alone."""
    if syms is None:
        return np.eye(3)[None]
    if isinstance(syms, SymmetrySet):
        return syms.transforms()[0]
    if isinstance(syms, tuple) and len(syms) == 2:
        syms = syms[0]  # only the rotations enter the rotation error
    R = _np(syms)
    if R.shape[-2:] != (3, 3) or R.size == 0:
        raise ValueError(f"a symmetry set must hold (S, 3, 3) rotations, got {R.shape}")
    return R.reshape(-1, 3, 3)


def _sym_translations(syms: Any) -> np.ndarray:
    """``t_S (S, 3)`` of one symmetry set (zeros when it gives rotations only, or for None)."""
    if isinstance(syms, SymmetrySet):
        return syms.transforms()[1]
    if isinstance(syms, tuple) and len(syms) == 2:
        return _np(syms[1]).reshape(-1, 3)
    return np.zeros((len(_sym_rotations(syms)), 3))


def symmetric_translation_deltas(t_est: Any, R_gt: Any, t_gt: Any, syms: Any = None) -> np.ndarray:
    """``(N, S, 3)`` candidate differences ``t_est − (t_gt + R_gt t_S)`` over each target's symmetry
    set (the authors' symmetric translation error, ``teS``, takes the smallest norm). ``syms``: one
    set for all targets or a list with one per target; a set with translations zero (or none) gives
    the plain ``t_est − t_gt``. Sets of different sizes are padded with their first member."""
    tE, tG = _np(t_est).reshape(-1, 3), _np(t_gt).reshape(-1, 3)
    Rg = _np(R_gt).reshape(-1, 3, 3)
    N = len(tE)
    sets = syms if isinstance(syms, list) else [syms] * N
    if len(sets) != N:
        raise ValueError(f"{len(sets)} symmetry sets for {N} targets")
    ts = [_sym_translations(s) for s in sets]
    S = max((len(t) for t in ts), default=1)
    T = (
        np.stack([np.concatenate([t, np.repeat(t[:1], S - len(t), 0)]) for t in ts])
        if N
        else np.zeros((0, S, 3))
    )
    return tE[:, None, :] - (tG[:, None, :] + np.einsum("nij,nsj->nsi", Rg, T))


def symmetric_rotation_errors_deg(R_est: Any, R_gt: Any, syms: Any = None) -> np.ndarray:
    """``min_{S} ∠(R_est (R_gt R_S)ᵀ)`` in degrees, ``(N,)``, for ``R (N, 3, 3)`` (or ``(3, 3)``).

    ``syms``: None (no symmetry); ONE set for all targets — a :class:`~posediff.symmetry.SymmetrySet`,
    the ``(R_S, t_S)`` tuple of :func:`~posediff.metrics.bop.symmetry_transforms` (``t_S`` is ignored)
    or an array ``R_S (S, 3, 3)``;
    or a ``list`` of N such sets, one per target (a set object repeated in the list is evaluated in
    one go). Continuous symmetries enter as their discretised set, so the error can exceed the exact
    one by up to half a discretisation step."""
    Re, Rg = _np(R_est).reshape(-1, 3, 3), _np(R_gt).reshape(-1, 3, 3)
    if len(Re) != len(Rg):
        raise ValueError(f"R_est has {len(Re)} rotations, R_gt {len(Rg)}")
    N = len(Re)
    groups: dict[int, tuple[Any, list[int]]] = {}
    if isinstance(syms, list):
        if len(syms) != N:
            raise ValueError(f"a list of symmetry sets needs one per target ({N}), got {len(syms)}")
        for i, s in enumerate(syms):
            groups.setdefault(id(s), (s, []))[1].append(i)
    else:
        groups[0] = (syms, list(range(N)))
    out = np.empty(N)
    for s, idx in groups.values():  # the smallest angle over a set: posediff.symmetry.min_angle_deg
        sel = np.asarray(idx, dtype=np.int64)
        out[sel] = min_angle_deg(Re[sel], Rg[sel], _sym_rotations(s))
    return out


def _label(x: float) -> str:
    return f"{x:g}"


def pose_recalls(
    R_est: Any,
    t_est: Any,
    R_gt: Any,
    t_gt: Any,
    syms: Any = None,
    rot_thresholds_deg: Sequence[float] = (2.0, 5.0, 10.0),
    trans_thresholds_mm: Sequence[float] = (20.0, 50.0, 100.0),
) -> dict[str, float]:
    """The paper's recalls (Hsiao et al., CVPR 2024, Table 3) over N targets, each strictly below
    the threshold: ``R@θ`` — symmetry-aware rotation error (:func:`symmetric_rotation_errors_deg`)
    ``< θ`` degrees; ``T@Xcm`` — ``min_S ‖t_est − (t_gt + R_gt t_S)‖ < X`` (the authors' ``teS``;
    the plain ``‖t_est − t_gt‖`` for symmetries without translation; translations in mm, labels in cm:
    20 mm → ``T@2cm``); ``x@Xcm`` / ``y@Xcm`` / ``z@Xcm`` — ``min_S |Δ_x|`` etc. ``< X`` with ``Δ`` the same
    difference (the authors' ``teSx`` zero the other components of ``t_est`` and ``t_gt`` but not of
    ``R_gt t_S``; both agree when ``t_S = 0``, as for T-LESS). ``R (N, 3, 3)``,
    ``t (N, 3)``; NaN poses (missing estimates) count as misses; N = 0 gives NaN."""
    Re, Rg = _np(R_est).reshape(-1, 3, 3), _np(R_gt).reshape(-1, 3, 3)
    tE, tG = _np(t_est).reshape(-1, 3), _np(t_gt).reshape(-1, 3)
    if not len(Re) == len(Rg) == len(tE) == len(tG):
        raise ValueError(f"pose counts differ: {len(Re)}, {len(tE)}, {len(Rg)}, {len(tG)}")
    N = len(Re)
    out: dict[str, float] = {}
    rot = symmetric_rotation_errors_deg(Re, Rg, syms) if N else np.zeros(0)
    deltas = symmetric_translation_deltas(tE, Rg, tG, syms)  # (N, S, 3)
    with np.errstate(invalid="ignore"):
        dist = np.linalg.norm(deltas, axis=-1).min(axis=1) if N else np.zeros(0)
        d = np.abs(deltas).min(axis=1) if N else np.zeros((0, 3))

    def frac(ok: np.ndarray) -> float:
        return float(ok.mean()) if N else math.nan

    with np.errstate(invalid="ignore"):
        for th in rot_thresholds_deg:
            out[f"R@{_label(th)}"] = frac(rot < th)
        for th in trans_thresholds_mm:
            out[f"T@{_label(th / 10.0)}cm"] = frac(dist < th)
        for k, axis in enumerate("xyz"):
            for th in trans_thresholds_mm:
                out[f"{axis}@{_label(th / 10.0)}cm"] = frac(d[:, k] < th)
    return out


# --------------------------------------------------------------------------------------------------
# Results CSV
# --------------------------------------------------------------------------------------------------

CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
TIME_TOLERANCE_S = 1e-3  # the toolkit's tolerance between the times of one image's estimates
#: How far an estimate's ``R`` may be from a rotation: ``max |RᵀR − I| ≤ ROTATION_TOLERANCE``
#: (elementwise) and ``|det R − 1| ≤ ROTATION_TOLERANCE``. Results are written with 6-9 significant
#: digits (float32 printed: RᵀR − I ~ 1e-7); even 4 decimals (each entry off by ≤ 5e-5) stay below
#: ~3e-4. Refused: a scaled R (R·s with |s − 1| > ~3.3e-4, as det R = s³; e.g. R×2), a reflection
#: (det −1), zeros, a garbled matrix. The BOP toolkit (``inout.load_bop_results``) checks nothing
#: here: it feeds any nine numbers to the errors, and a scaled R keeps its rotation angle.
ROTATION_TOLERANCE = 1e-3


class BopResultsError(ValueError):
    """A BOP19 results file or estimate that cannot be scored (one line naming the file and line,
    or the row)."""


def rotation_problem(R: Any, tol: float = ROTATION_TOLERANCE) -> str | None:
    """Why ``R`` (9 numbers, row-major) is not a rotation within ``tol`` (:data:`ROTATION_TOLERANCE`),
    or ``None`` when it is one."""
    M = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(M).all():
        return "R has non-finite numbers"
    gram = M.T @ M
    err = float(np.abs(gram - np.eye(3)).max())
    det = float(np.linalg.det(M))
    if err > tol:
        if not M.any():
            return "R is all zeros, not a rotation"
        scale = math.sqrt(max(float(np.trace(gram)) / 3.0, 0.0))
        scaled = scale > 0 and float(np.abs(gram / scale**2 - np.eye(3)).max()) <= tol
        what = f"R looks like a rotation scaled by {scale:.6g}" if scaled else "R is not orthonormal"
        return f"{what} (max |RᵀR − I| = {err:.3g} > {tol:g}{', det = ' + format(det, '.3g') if det < 0 else ''})"
    if abs(det - 1.0) > tol:
        kind = "a reflection" if det < 0 else "not a rotation"
        return f"R has det {det:.6g} ({kind}; a rotation has det +1 within {tol:g})"
    return None


def check_rotation(R: Any, where: str, tol: float = ROTATION_TOLERANCE) -> None:
    """Refuse an ``R`` that is no rotation (:func:`rotation_problem`) with one line
    (:class:`BopResultsError`) starting with ``where``."""
    problem = rotation_problem(R, tol)
    if problem is not None:
        raise BopResultsError(
            f"{where}: {problem}; R must be a rotation (orthonormal, det +1, within {tol:g}) model → camera, "
            "9 numbers row-major"
        )


@dataclass(eq=False)
class BopEstimate:
    """One row of a BOP19 results file: ``R (3, 3)`` model → camera, ``t (3,)`` in mm, ``time`` the
    seconds spent on the whole image (the same for all its estimates; −1 if unknown)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0
    #: where the row came from, for messages (``read_bop19_csv``: ``"path:line"``); not compared
    where: str = field(default="", compare=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("scene_id", "im_id", "obj_id"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v:
                raise ValueError(f"{name} must be an integer, got {v!r}")
            setattr(self, name, int(v))
        self.score, self.time = float(self.score), float(self.time)
        R, t = _np(self.R), _np(self.t)
        if R.size != 9 or t.size != 3:
            raise ValueError(f"R must have 9 numbers and t 3, got {R.shape} and {t.shape}")
        self.R, self.t = R.reshape(3, 3), t.reshape(3)
        if not (np.isfinite(self.R).all() and np.isfinite(self.t).all() and math.isfinite(self.score)):
            raise ValueError(f"non-finite R, t or score in the estimate of obj {self.obj_id}")
        if not math.isfinite(self.time):
            raise ValueError(f"time must be finite (−1 if unknown), got {self.time}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, BopEstimate):
            return NotImplemented
        return (
            (self.scene_id, self.im_id, self.obj_id, self.score, self.time)
            == (other.scene_id, other.im_id, other.obj_id, other.score, other.time)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
        )

    __hash__ = None  # type: ignore[assignment]


def _as_estimate(row: BopEstimate | Mapping[str, Any]) -> BopEstimate:
    if isinstance(row, BopEstimate):
        return row
    return BopEstimate(
        **{k: row[k] for k in ("scene_id", "im_id", "obj_id", "score", "R", "t")}, time=row.get("time", -1.0)
    )


def _check_times(times: dict[tuple[int, int], float], e: BopEstimate, where: str) -> None:
    key = (e.scene_id, e.im_id)
    first = times.setdefault(key, e.time)
    if abs(first - e.time) > TIME_TOLERANCE_S:
        raise BopResultsError(
            f"{where}: scene {e.scene_id} image {e.im_id} has time {e.time} but also {first}; BOP19 "
            "needs one time per image"
        )


def write_bop19_csv(path: str | Path, rows: Iterable[BopEstimate | Mapping[str, Any]]) -> Path:
    """Write a BOP19 results file (``CSV_HEADER``; R as 9 numbers row-major and t as 3 numbers, mm,
    separated by spaces; shortest round-trip floats) atomically. ``rows``: :class:`BopEstimate` or
    mappings with its field names (``time`` optional, −1). Raises ValueError when the estimates of one
    image carry different times."""
    lines = [CSV_HEADER]
    times: dict[tuple[int, int], float] = {}
    for k, row in enumerate(rows):
        e = _as_estimate(row)
        _check_times(times, e, f"{path}: row {k}")
        R = " ".join(repr(float(x)) for x in e.R.reshape(-1))
        t = " ".join(repr(float(x)) for x in e.t)
        lines.append(f"{e.scene_id},{e.im_id},{e.obj_id},{e.score!r},{R},{t},{e.time!r}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _utf8_text(path: str | Path) -> str:
    """The file's text: UTF-8, a leading byte-order mark (Excel's "CSV UTF-8") dropped; other bytes
    refused with one line naming the file, line and column (:class:`BopResultsError`)."""
    import codecs

    data = Path(path).read_bytes()
    skip = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        return data[skip:].decode("utf-8")
    except UnicodeDecodeError as e:
        pos = skip + e.start
        line = data.count(b"\n", 0, pos) + 1
        column = pos - (data.rfind(b"\n", 0, pos) + 1) + 1
        raise BopResultsError(
            f"{path}:{line}: not UTF-8 text (byte 0x{data[pos]:02x} at column {column}); a BOP19 results "
            "CSV is plain ASCII / UTF-8: save it as UTF-8"
        ) from None


def read_bop19_csv(path: str | Path) -> list[BopEstimate]:
    """Parse a BOP19 results file (UTF-8, a byte-order mark allowed; the header line is optional, as
    for the toolkit; blank lines are skipped). Raises a one-line :class:`BopResultsError` naming the
    file and line on a non-UTF-8 file, a malformed row, an ``R`` that is no rotation
    (:data:`ROTATION_TOLERANCE`) or when one image's estimates carry different times."""
    out: list[BopEstimate] = []
    times: dict[tuple[int, int], float] = {}
    text = _utf8_text(path)
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        where = f"{path}:{n}"
        if not out and line.startswith("scene_id"):
            if line.replace(" ", "") != CSV_HEADER:
                raise BopResultsError(f"{where}: header {line!r}, expected {CSV_HEADER!r}")
            continue
        fields = line.split(",")
        if len(fields) != 7:
            raise BopResultsError(f"{where}: {len(fields)} comma-separated fields, expected 7 ({CSV_HEADER})")
        try:
            R = [float(x) for x in fields[4].split()]
            t = [float(x) for x in fields[5].split()]
            if len(R) != 9 or len(t) != 3:
                raise ValueError(f"R has {len(R)} numbers (expected 9), t {len(t)} (expected 3)")
            e = BopEstimate(
                int(fields[0]),
                int(fields[1]),
                int(fields[2]),
                float(fields[3]),
                np.array(R),
                np.array(t),
                float(fields[6]),
                where=where,
            )
        except ValueError as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise BopResultsError(f"{where}: {msg}") from None
        check_rotation(e.R, where)
        _check_times(times, e, where)
        out.append(e)
    return out


__all__ = [
    "BOP19",
    "CSV_HEADER",
    "ROTATION_TOLERANCE",
    "VSD_DELTAS",
    "BopEstimate",
    "BopResultsError",
    "Bop19Protocol",
    "ImageObjectErrors",
    "Matches",
    "ar_from_paired_errors",
    "average_recall",
    "check_rotation",
    "match",
    "mspd_correct",
    "mssd_correct",
    "pose_recalls",
    "read_bop19_csv",
    "rotation_problem",
    "symmetric_rotation_errors_deg",
    "vsd_correct",
    "write_bop19_csv",
]
