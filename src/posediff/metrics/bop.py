"""BOP pose-error functions (Hodaň et al., "BOP Challenge 2020 on 6D Object Localization", ECCVW
2020; Hodaň, Matas, Obdržálek, "On Evaluation of 6D Object Pose Estimation", ECCVW 2016 for VSD; the
BOP toolkit's definitions), in numpy.

Inputs may be numpy arrays, torch tensors (moved to the CPU, computed in float64) or nested sequences.
Points ``pts (N, 3)`` are in the model frame (mm for BOP models); poses ``R``, ``t`` map model →
camera (``t`` in the units of ``pts``). Every pose-error function takes either ONE pose pair —
``R (3, 3)``, ``t (3,)`` (or a column ``(3, 1)``), returning a ``float`` — or a BATCH —
``R (B, 3, 3)``, ``t (B, 3)``, returning a numpy array ``(B,)``; a single pose next to batched ones
is broadcast (e.g. one ground truth against B estimates). ``pts`` and the symmetry set are shared by
the whole batch (one object); the camera matrix ``K`` may be ``(3, 3)`` or ``(B, 3, 3)``.

* :func:`symmetry_transforms` — the set S of symmetry transformations ``(R_S, t_S)`` of a
  ``models_info`` entry: the identity first, then each discrete symmetry (4×4, row-major), and each
  continuous one (``axis`` through ``offset``) discretised into ``n = ceil(π / max_sym_disc_step)``
  rotations by ``2π k / n`` — ``R_k = Rot(axis, 2πk/n)``, ``t_k = offset − R_k·offset`` — composed with
  every discrete one: ``(R_c R_d, R_c t_d + t_c)``, k = 0 … n − 1 — the same set, in the same
  order, as the BOP toolkit's ``misc.get_symmetry_transformations`` (which also runs k from 0, so
  the identity and every ``R_d`` are members).
* :func:`mssd` — Maximum Symmetry-aware Surface Distance (units of ``pts``):
  ``min_{S} max_{x ∈ pts} ‖(R_e x + t_e) − (R_g (R_S x + t_S) + t_g)‖``. With ``diameter`` given, the
  toolkit's short-cut: ``inf`` when ``‖t_e − t_g‖ ≥ diameter`` (the bounding spheres of radius
  diameter/2 around the two poses' origins do not overlap), without evaluating the points.
* :func:`mspd` — Maximum Symmetry-aware Projection Distance: the same with the 2-D distance between
  the projections ``π_K(X) = (K X)_{xy} / (K X)_z`` (pixels).
* :func:`vsd` — Visible Surface Discrepancy on depth maps (BOP19 visibility, step cost), one error
  per τ: with ``D`` the distance from the camera centre of each pixel's surface point (depth →
  distance along the ray, :func:`depth_to_distance`), ``V̂`` / ``V̄`` the visible masks of the
  estimate / ground truth w.r.t. the test depth (tolerance δ),
  ``e_τ = (|{p ∈ V̂ ∩ V̄ : |D̂ − D̄| ≥ τ}| + |V̂ ∪ V̄| − |V̂ ∩ V̄|) / |V̂ ∪ V̄|``, and 1 when the union
  is empty. Distances are divided by the diameter with ``normalized_by_diameter`` (BOP19: τ is then a
  fraction of the diameter). Given ``t_est`` and ``t_gt``, the toolkit's short-cut: all errors are 1
  when the projections of the bounding spheres (radius diameter/2) do not overlap
  (:func:`sphere_projections_overlap`).
* :func:`sphere_projections_overlap` — the toolkit's conservative test: the sphere centres projected
  to the normalised image plane, ``(x/z, y/z)``, overlap iff their distance is
  ``< radius · (1/z₁ + 1/z₂)``.
* :func:`add` — mean distance of corresponding points; :func:`adi` — mean distance from each
  ground-truth point to the nearest estimated point (ADD-S); :func:`re` — rotation error
  ``arccos((tr(R_e R_gᵀ) − 1)/2)`` in degrees; :func:`te` — translation error ``‖t_e − t_g‖`` (units of
  t).

Memory: MSSD / MSPD evaluate all ``B·S`` (pose, symmetry) pairs in chunks of about 2²⁰ transformed
points (tens of MB per temporary), e.g. S = 630 symmetries of a continuous object × 10 000 points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..symmetry import SymmetrySet
from ._arrays import as_float64 as _np

_CHUNK_POINTS = 1 << 20  # (pose, symmetry, point) triples per chunk: a (C, N, 3) float64 array ≈ 24 MB
_CHUNK_PIXELS = 1 << 21  # pixels per VSD chunk: a float64 map ≈ 16 MB
_CHUNK_PAIRS = 1 << 22  # point pairs per ADI block: a float64 matrix ≈ 32 MB


def _rot(R: Any, name: str) -> np.ndarray:
    a = _np(R)
    if a.ndim not in (2, 3) or a.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must be (3, 3) or (B, 3, 3), got {a.shape}")
    return a


def _vec(t: Any, name: str) -> np.ndarray:
    a = _np(t)
    if a.ndim in (2, 3) and a.shape[-2:] == (3, 1):  # column vectors, as BOP files store them
        a = a[..., 0]
    if a.ndim not in (1, 2) or a.shape[-1] != 3:
        raise ValueError(f"{name} must be (3,) or (B, 3), got {a.shape}")
    return a


def _batch_size(named: dict[str, np.ndarray], single_ndim: dict[str, int]) -> tuple[int, bool]:
    sizes = {k: a.shape[0] for k, a in named.items() if a.ndim > single_ndim[k]}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"batch sizes differ: {sizes}")
    return (next(iter(sizes.values())) if sizes else 1), bool(sizes)


def _poses(R_est: Any, t_est: Any, R_gt: Any, t_gt: Any):  # noqa: ANN202 - R, t, R, t (B-batched), batched
    arrays = {
        "R_est": _rot(R_est, "R_est"),
        "t_est": _vec(t_est, "t_est"),
        "R_gt": _rot(R_gt, "R_gt"),
        "t_gt": _vec(t_gt, "t_gt"),
    }
    B, batched = _batch_size(arrays, {"R_est": 2, "t_est": 1, "R_gt": 2, "t_gt": 1})
    Re, Rg = (np.broadcast_to(arrays[k], (B, 3, 3)) for k in ("R_est", "R_gt"))
    te, tg = (np.broadcast_to(arrays[k], (B, 3)) for k in ("t_est", "t_gt"))
    return Re, te, Rg, tg, batched


def _points(pts: Any) -> np.ndarray:
    p = _np(pts)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"pts must be (N, 3) with N ≥ 1, got {p.shape}")
    return p


def _syms(syms: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(R_S (S, 3, 3), t_S (S, 3))`` from a :class:`~posediff.symmetry.SymmetrySet` (discretised at
    BOP's 0.01), :func:`symmetry_transforms`' pair, or ``None`` (identity)."""
    if syms is None:
        return np.eye(3)[None], np.zeros((1, 3))
    if isinstance(syms, SymmetrySet):
        return syms.transforms()
    if len(syms) != 2:
        raise ValueError("syms must be the pair (R (S, 3, 3), t (S, 3)) returned by symmetry_transforms")
    Rs, ts = _np(syms[0]).reshape(-1, 3, 3), _np(syms[1]).reshape(-1, 3)
    if len(Rs) != len(ts) or len(Rs) == 0:
        raise ValueError(f"syms: {len(Rs)} rotations but {len(ts)} translations")
    return Rs, ts


def _per_batch(x: Any, B: int, name: str) -> np.ndarray:
    a = _np(x)
    if a.ndim > 1 or (a.ndim == 1 and len(a) not in (1, B)):
        raise ValueError(f"{name} must be a scalar or ({B},), got {a.shape}")
    return np.broadcast_to(a.reshape(-1), (B,))


def _cameras(K: Any, B: int) -> np.ndarray:
    k = _np(K)
    if k.shape == (3, 3):
        return np.broadcast_to(k, (B, 3, 3))
    if k.shape == (B, 3, 3):
        return k
    raise ValueError(f"K must be (3, 3) or ({B}, 3, 3), got {k.shape}")


def _out(x: np.ndarray, batched: bool) -> np.ndarray | float:
    return x if batched else float(x[0])


def symmetry_transforms(
    model_info: dict[str, Any], max_sym_disc_step: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """``(R (S, 3, 3), t (S, 3))``: the BOP symmetry set of a ``models_info`` entry (module docstring);
    ``t`` in the units of the model (mm). Shorthand for
    ``SymmetrySet.from_models_info(model_info).transforms(max_sym_disc_step)``
    (:class:`posediff.symmetry.SymmetrySet`)."""
    return SymmetrySet.from_models_info(model_info).transforms(max_sym_disc_step)


def _apply(P: np.ndarray, A: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``A_k x + c_k`` for every point ``x`` of ``P (N, 3)`` and every ``(A (C, 3, 3), c (C, 3))``:
    ``(N, C, 3)``, as one ``(N, 3) × (3, 3C)`` matrix product (a batch of 3×3 products is slow)."""
    C = len(A)
    W = A.transpose(2, 0, 1).reshape(3, 3 * C)  # W[j, 3k + i] = A[k, i, j]
    return (P @ W).reshape(len(P), C, 3) + c[None]


def _min_over_syms(B: int, S: int, N: int, chunk_error) -> np.ndarray:  # noqa: ANN001
    """``min_s chunk_error(b, s)`` for every b, evaluating the flat (b, s) pairs in chunks."""
    out = np.empty(B * S)
    step = max(1, _CHUNK_POINTS // N)
    for lo in range(0, B * S, step):
        idx = np.arange(lo, min(lo + step, B * S))
        out[idx] = chunk_error(idx // S, idx % S)
    return out.reshape(B, S).min(axis=1)


def mssd(R_est, t_est, R_gt, t_gt, pts, syms, *, diameter=None) -> np.ndarray | float:  # noqa: ANN001
    """Maximum Symmetry-aware Surface Distance (units of ``pts`` / ``t``; module docstring):
    ``float`` for one pose pair, ``(B,)`` for a batch. ``syms`` is :func:`symmetry_transforms`' pair
    (``None``: no symmetry). ``diameter`` (scalar or ``(B,)``, units of t): the toolkit's short-cut —
    ``inf`` where ``‖t_est − t_gt‖ ≥ diameter``."""
    R_e, t_e, R_g, t_g, batched = _poses(R_est, t_est, R_gt, t_gt)
    P, (SR, St) = _points(pts), _syms(syms)
    B, S, N = len(R_e), len(SR), len(P)
    todo = np.ones(B, dtype=bool)
    if diameter is not None:
        todo = np.linalg.norm(t_e - t_g, axis=1) < _per_batch(diameter, B, "diameter")
    err = np.full(B, np.inf)
    if todo.any():
        R_e, t_e, R_g, t_g = R_e[todo], t_e[todo], R_g[todo], t_g[todo]

        def chunk(b: np.ndarray, s: np.ndarray) -> np.ndarray:
            # est − gt_sym = (R_e − R_g R_S) x + (t_e − R_g t_S − t_g), all pairs in one matrix product
            A = R_e[b] - R_g[b] @ SR[s]
            c = t_e[b] - np.einsum("cij,cj->ci", R_g[b], St[s]) - t_g[b]
            D = _apply(P, A, c)  # (N, C, 3)
            return np.sqrt(np.einsum("nci,nci->nc", D, D).max(axis=0))

        err[todo] = _min_over_syms(int(todo.sum()), S, N, chunk)
    return _out(err, batched)


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> np.ndarray | float:  # noqa: ANN001
    """Maximum Symmetry-aware Projection Distance (pixels; module docstring): ``float`` for one pose
    pair, ``(B,)`` for a batch; ``K (3, 3)`` or ``(B, 3, 3)``."""
    R_e, t_e, R_g, t_g, batched = _poses(R_est, t_est, R_gt, t_gt)
    P, (SR, St) = _points(pts), _syms(syms)
    B, S, N = len(R_e), len(SR), len(P)
    Ks = _cameras(K, B)

    def project(M: np.ndarray, m: np.ndarray) -> np.ndarray:  # K·(R x + t) = M x + m → (N, C, 2)
        Y = _apply(P, M, m)
        return Y[..., :2] / Y[..., 2:3]

    def chunk(b: np.ndarray, s: np.ndarray) -> np.ndarray:
        ub, inv = np.unique(b, return_inverse=True)
        est = project(Ks[ub] @ R_e[ub], np.einsum("cij,cj->ci", Ks[ub], t_e[ub]))[:, inv]
        Rgs = R_g[b] @ SR[s]
        tgs = np.einsum("cij,cj->ci", R_g[b], St[s]) + t_g[b]
        d = est - project(Ks[b] @ Rgs, np.einsum("cij,cj->ci", Ks[b], tgs))
        return np.sqrt(np.einsum("nci,nci->nc", d, d).max(axis=0))

    return _out(_min_over_syms(B, S, N, chunk), batched)


def depth_to_distance(depth, K) -> np.ndarray:  # noqa: ANN001
    """Per-pixel distance from the camera centre of the surface point seen at depth ``depth``:
    ``D(u, v) = depth(u, v) · √(((u − c_x)/f_x)² + ((v − c_y)/f_y)² + 1)``; ``depth (H, W)`` with
    ``K (3, 3)``, or ``(B, H, W)`` with ``K (3, 3)`` or ``(B, 3, 3)`` (units of depth)."""
    d = _np(depth)
    if d.ndim not in (2, 3):
        raise ValueError(f"depth must be (H, W) or (B, H, W), got {d.shape}")
    k = _np(K)
    if k.shape != (3, 3) and not (d.ndim == 3 and k.shape == (len(d), 3, 3)):
        raise ValueError(f"K {k.shape} does not fit depth {d.shape}")
    k = k.reshape(-1, 3, 3)
    h, w = d.shape[-2:]
    x = (np.arange(w, dtype=np.float64)[None, None, :] - k[:, 0, 2, None, None]) / k[:, 0, 0, None, None]
    y = (np.arange(h, dtype=np.float64)[None, :, None] - k[:, 1, 2, None, None]) / k[:, 1, 1, None, None]
    scale = np.sqrt(x * x + y * y + 1.0)  # (Bk, H, W)
    return d * (scale[0] if d.ndim == 2 else scale)


def _visible(d_test: np.ndarray, d_model: np.ndarray, delta: float) -> np.ndarray:
    """BOP19 visibility: the model surface exists and is not behind the test surface by more than δ
    (pixels without a test measurement count as visible)."""
    return (d_model > 0) & ((d_model - d_test <= delta) | (d_test == 0))


def sphere_projections_overlap(radius, t1, t2) -> np.ndarray | bool:  # noqa: ANN001
    """Whether the image projections of two spheres of ``radius`` centred at ``t1`` and ``t2``
    (camera frame, z > 0) overlap — the BOP toolkit's conservative test: with the centres projected to
    the normalised image plane ``p = (x/z, y/z)``, ``‖p₁ − p₂‖ < radius · (1/z₁ + 1/z₂)``.
    ``t (3,)`` → ``bool``; ``t (B, 3)`` (either) → ``(B,)`` bool; ``radius`` scalar or ``(B,)``."""
    a, b = _vec(t1, "t1"), _vec(t2, "t2")
    B, batched = _batch_size({"t1": a, "t2": b}, {"t1": 1, "t2": 1})
    a, b = np.broadcast_to(a, (B, 3)), np.broadcast_to(b, (B, 3))
    dist = np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1)
    overlap = dist < _per_batch(radius, B, "radius") * (1.0 / a[:, 2] + 1.0 / b[:, 2])
    return overlap if batched else bool(overlap[0])


def vsd(
    depth_est,  # noqa: ANN001
    depth_gt,  # noqa: ANN001
    depth_test,  # noqa: ANN001
    K,  # noqa: ANN001
    delta: float,
    taus,  # noqa: ANN001
    diameter,  # noqa: ANN001
    normalized_by_diameter: bool = True,
    cost: str = "step",
    *,
    t_est=None,  # noqa: ANN001
    t_gt=None,  # noqa: ANN001
) -> list[float] | np.ndarray:
    """Visible Surface Discrepancy (Hodaň et al., ECCVW 2016; BOP19 variant; module docstring).

    Depth maps ``(H, W)`` → one error per τ in ``taus`` (a list of floats); ``(B, H, W)`` → a numpy
    array ``(B, len(taus))``. Depths in the units of δ (mm for BOP; 0 = no surface); ``K (3, 3)`` or
    ``(B, 3, 3)``; ``diameter`` scalar or ``(B,)`` (units of depth; τ is a fraction of it with
    ``normalized_by_diameter``, else in depth units). Given ``t_est`` and ``t_gt`` (``(3,)`` or
    ``(B, 3)``, units of depth), pairs whose bounding-sphere projections (radius diameter/2) do not
    overlap get error 1 for every τ without looking at the depth maps (the toolkit's short-cut, which
    spares rendering: the depth maps of those pairs may then be anything of the right shape).
    """
    if cost != "step":
        raise ValueError(f"unknown VSD cost {cost!r}; available: step (BOP19)")
    de, dg, dt = _np(depth_est), _np(depth_gt), _np(depth_test)
    shapes = {de.shape, dg.shape, dt.shape}
    if len(shapes) != 1:
        raise ValueError(f"depth maps differ in shape: {sorted(shapes)}")
    if de.ndim not in (2, 3):
        raise ValueError(f"depth maps must be (H, W) or (B, H, W), got {de.shape}")
    batched = de.ndim == 3
    if not batched:
        de, dg, dt = de[None], dg[None], dt[None]
    B, H, W = de.shape
    Ks = _cameras(K, B)
    tau = _np(taus).reshape(-1)
    diam = _per_batch(diameter, B, "diameter")
    if normalized_by_diameter and not (diam > 0).all():
        raise ValueError("diameter must be > 0 with normalized_by_diameter")
    err = np.ones((B, len(tau)))
    todo = np.ones(B, dtype=bool)
    if (t_est is None) != (t_gt is None):
        raise ValueError("give both t_est and t_gt (the bounding-sphere short-cut) or neither")
    if t_est is not None:
        todo = np.broadcast_to(sphere_projections_overlap(0.5 * diam, t_est, t_gt), (B,))
    idx_all = np.flatnonzero(todo)
    step = max(1, _CHUNK_PIXELS // max(1, H * W))
    for lo in range(0, len(idx_all), step):
        idx = idx_all[lo : lo + step]
        D_test = depth_to_distance(dt[idx], Ks[idx])
        D_gt = depth_to_distance(dg[idx], Ks[idx])
        D_est = depth_to_distance(de[idx], Ks[idx])
        vis_gt = _visible(D_test, D_gt, delta)
        vis_est = _visible(D_test, D_est, delta) | (vis_gt & (D_est > 0))
        inter = vis_gt & vis_est
        union = (vis_gt | vis_est).sum(axis=(1, 2))
        outside = union - inter.sum(axis=(1, 2))
        cost_map = np.abs(D_gt - D_est)
        if normalized_by_diameter:
            cost_map /= diam[idx, None, None]
        bad = np.stack([(inter & (cost_map >= t)).sum(axis=(1, 2)) for t in tau], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            e = (bad + outside[:, None]) / union[:, None]
        err[idx] = np.where(union[:, None] == 0, 1.0, e)
    return err if batched else [float(e) for e in err[0]]


def add(R_est, t_est, R_gt, t_gt, pts) -> np.ndarray | float:  # noqa: ANN001
    """Average Distance of model points (corresponding points), ``mean_x ‖(R_e x + t_e) − (R_g x + t_g)‖``
    (units of ``pts``): ``float`` or ``(B,)``."""
    R_e, t_e, R_g, t_g, batched = _poses(R_est, t_est, R_gt, t_gt)
    P = _points(pts)
    B, N = len(R_e), len(P)
    out = np.empty(B)
    step = max(1, _CHUNK_POINTS // N)
    for lo in range(0, B, step):
        sl = slice(lo, lo + step)
        D = P @ (R_e[sl] - R_g[sl]).transpose(0, 2, 1) + (t_e[sl] - t_g[sl])[:, None, :]
        out[sl] = np.sqrt(np.einsum("cni,cni->cn", D, D)).mean(axis=1)
    return _out(out, batched)


def adi(R_est, t_est, R_gt, t_gt, pts) -> np.ndarray | float:  # noqa: ANN001
    """Average distance from each ground-truth model point to the nearest estimated one (ADD-S, for
    symmetric objects; units of ``pts``): ``float`` or ``(B,)``. The nearest point is found from
    ``‖g‖² + ‖e‖² − 2 g·e`` in blocks (no N×N×3 array), its distance recomputed exactly."""
    R_e, t_e, R_g, t_g, batched = _poses(R_est, t_est, R_gt, t_gt)
    P = _points(pts)
    N = len(P)
    out = np.empty(len(R_e))
    blk = max(1, _CHUNK_PAIRS // N)
    for b in range(len(R_e)):
        e, g = P @ R_e[b].T + t_e[b], P @ R_g[b].T + t_g[b]
        e2 = np.einsum("ni,ni->n", e, e)
        total = 0.0
        for lo in range(0, N, blk):
            gb = g[lo : lo + blk]
            j = (e2[None, :] - 2.0 * (gb @ e.T)).argmin(axis=1)  # + ‖g‖², constant per row
            total += np.linalg.norm(gb - e[j], axis=1).sum()
        out[b] = total / N
    return _out(out, batched)


def re(R_est, R_gt) -> np.ndarray | float:  # noqa: ANN001
    """Rotation error: the angle of ``R_est R_gtᵀ``, ``arccos((tr − 1)/2)`` in degrees: ``float`` for
    ``(3, 3)`` inputs, ``(B,)`` when either is ``(B, 3, 3)``."""
    a, b = _rot(R_est, "R_est"), _rot(R_gt, "R_gt")
    B, batched = _batch_size({"R_est": a, "R_gt": b}, {"R_est": 2, "R_gt": 2})
    a, b = np.broadcast_to(a, (B, 3, 3)), np.broadcast_to(b, (B, 3, 3))
    c = (np.einsum("bij,bij->b", a, b) - 1.0) / 2.0
    return _out(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))), batched)


def te(t_est, t_gt) -> np.ndarray | float:  # noqa: ANN001
    """Translation error ``‖t_est − t_gt‖`` (units of t): ``float`` or ``(B,)``."""
    a, b = _vec(t_est, "t_est"), _vec(t_gt, "t_gt")
    B, batched = _batch_size({"t_est": a, "t_gt": b}, {"t_est": 1, "t_gt": 1})
    return _out(np.linalg.norm(np.broadcast_to(a, (B, 3)) - np.broadcast_to(b, (B, 3)), axis=1), batched)


__all__ = [
    "add",
    "adi",
    "depth_to_distance",
    "mspd",
    "mssd",
    "re",
    "sphere_projections_overlap",
    "symmetry_transforms",
    "te",
    "vsd",
]
