"""BOP pose-error functions (Hodaň et al., "BOP Challenge 2020 on 6D Object Localization", ECCVW
2020; the BOP toolkit's definitions), in numpy, for one pose pair; points ``pts (N, 3)`` in the
model frame (mm for BOP models), poses ``R (3, 3)``, ``t (3,)`` map model → camera.

* :func:`symmetry_transforms` — the set S of symmetry transformations of a ``models_info``
  entry: the identity first, then each discrete symmetry (4×4, row-major), and each continuous one
  (``axis`` through ``offset``) discretised into ``n = ceil(π / max_sym_disc_step)`` rotations by
  ``2π k / n`` — ``R_k = Rot(axis, 2πk/n)``, ``t_k = offset − R_k·offset`` — composed with every
  discrete one: ``(R_c R_d, R_c t_d + t_c)``. (The toolkit starts k at 1; k = 0 adds the identity,
  which every set contains anyway.)
* :func:`mssd` — maximum symmetry-aware surface distance:
  ``min_{S} max_{x ∈ pts} ‖(R_e x + t_e) − (R_g (R_S x + t_S) + t_g)‖``.
* :func:`mspd` — the same with the 2-D distance between the projections by ``K`` (pixels).
* :func:`vsd` — Visible Surface Discrepancy on depth maps (BOP19 visibility, step cost), one error
  per τ: with ``D`` the distance from the camera centre of each pixel's surface point (depth → distance
  along the ray), ``V̂`` / ``V̄`` the visible masks of the estimate / ground truth w.r.t. the test depth
  (tolerance δ), ``e_τ = (|{p ∈ V̂ ∩ V̄ : |D̂ − D̄| ≥ τ}| + |V̂ ∪ V̄| − |V̂ ∩ V̄|) / |V̂ ∪ V̄|``, and 1 when
  the union is empty. Distances are divided by the diameter with ``normalized_by_diameter``.
* :func:`add` — mean distance of corresponding points; :func:`adi` — mean distance to the nearest
  point of the other set (ADD-S); :func:`re` — rotation error in degrees; :func:`te` —
  translation error (units of t).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def symmetry_transforms(
    model_info: dict[str, Any], max_sym_disc_step: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """``(R (S, 3, 3), t (S, 3))``: the BOP symmetry set of a ``models_info`` entry (module docstring)."""
    if max_sym_disc_step <= 0:
        raise ValueError(f"max_sym_disc_step must be > 0, got {max_sym_disc_step}")
    disc_R, disc_t = [np.eye(3)], [np.zeros(3)]
    for k, sym in enumerate(model_info.get("symmetries_discrete", [])):
        m = np.asarray(sym, dtype=np.float64)
        if m.size != 16:
            raise ValueError(f"symmetries_discrete[{k}] has {m.size} numbers, not 16 (a row-major 4×4)")
        m = m.reshape(4, 4)
        disc_R.append(m[:3, :3])
        disc_t.append(m[:3, 3])
    cont_R, cont_t = [], []
    for sym in model_info.get("symmetries_continuous", []):
        axis = np.asarray(sym["axis"], dtype=np.float64)
        offset = np.asarray(sym.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
        n = int(math.ceil(math.pi / max_sym_disc_step))
        for i in range(n):
            R = _rotation(axis, 2.0 * math.pi * i / n)
            cont_R.append(R)
            cont_t.append(offset - R @ offset)
    if not cont_R:
        return np.stack(disc_R), np.stack(disc_t)
    Rs, ts = [], []
    for Rd, td in zip(disc_R, disc_t, strict=True):
        for Rc, tc in zip(cont_R, cont_t, strict=True):
            Rs.append(Rc @ Rd)
            ts.append(Rc @ td + tc)
    return np.stack(Rs), np.stack(ts)


def _transform(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return pts @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64).reshape(1, 3)


def _project(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = pts @ np.asarray(K, dtype=np.float64).T
    return p[:, :2] / p[:, 2:3]


def _gt_under_syms(R_gt, t_gt, syms):  # noqa: ANN001, ANN202 - (S,3,3), (S,3) of the symmetric gt poses
    Rs, ts = syms
    R_gt = np.asarray(R_gt, dtype=np.float64)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(3)
    return R_gt @ Rs, ts @ R_gt.T + t_gt


def mssd(R_est, t_est, R_gt, t_gt, pts, syms) -> float:  # noqa: ANN001
    """Maximum Symmetry-aware Surface Distance (units of ``pts``/``t``)."""
    pts = np.asarray(pts, dtype=np.float64)
    est = _transform(pts, R_est, t_est)
    Rg, tg = _gt_under_syms(R_gt, t_gt, syms)
    return float(
        min(np.linalg.norm(est - _transform(pts, R, t), axis=1).max() for R, t in zip(Rg, tg, strict=True))
    )


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> float:  # noqa: ANN001
    """Maximum Symmetry-aware Projection Distance (pixels)."""
    pts = np.asarray(pts, dtype=np.float64)
    est = _project(_transform(pts, R_est, t_est), K)
    Rg, tg = _gt_under_syms(R_gt, t_gt, syms)
    return float(
        min(
            np.linalg.norm(est - _project(_transform(pts, R, t), K), axis=1).max()
            for R, t in zip(Rg, tg, strict=True)
        )
    )


def depth_to_distance(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per-pixel distance from the camera centre of the surface point seen at depth ``depth (H, W)``."""
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(x * x + y * y + 1.0)


def _visible(d_test: np.ndarray, d_model: np.ndarray, delta: float) -> np.ndarray:
    """BOP19 visibility: the model surface exists and is not behind the test surface by more than δ
    (pixels without a test measurement count as visible)."""
    return (d_model > 0) & ((d_model - d_test <= delta) | (d_test == 0))


def vsd(
    depth_est,  # noqa: ANN001
    depth_gt,  # noqa: ANN001
    depth_test,  # noqa: ANN001
    K,  # noqa: ANN001
    delta: float,
    taus,  # noqa: ANN001
    diameter: float,
    normalized_by_diameter: bool = True,
    cost: str = "step",
) -> list[float]:
    """Visible Surface Discrepancy (module docstring): one error per τ in ``taus``. Depth maps are
    ``(H, W)`` in the units of δ (0 = no surface); ``K`` the camera matrix."""
    if cost != "step":
        raise ValueError(f"unknown VSD cost {cost!r}; available: step (BOP19)")
    K = np.asarray(K, dtype=np.float64)
    shapes = {np.shape(depth_est), np.shape(depth_gt), np.shape(depth_test)}
    if len(shapes) != 1:
        raise ValueError(f"depth maps differ in shape: {sorted(shapes)}")
    d_test, d_gt, d_est = (depth_to_distance(d, K) for d in (depth_test, depth_gt, depth_est))
    vis_gt = _visible(d_test, d_gt, delta)
    vis_est = _visible(d_test, d_est, delta) | (vis_gt & (d_est > 0))
    inter = vis_gt & vis_est
    union = int((vis_gt | vis_est).sum())
    if union == 0:
        return [1.0 for _ in taus]
    dists = np.abs(d_gt[inter] - d_est[inter])
    if normalized_by_diameter:
        dists = dists / float(diameter)
    outside = union - int(inter.sum())
    return [float(((dists >= tau).sum() + outside) / union) for tau in taus]


def add(R_est, t_est, R_gt, t_gt, pts) -> float:  # noqa: ANN001
    """Average Distance of model points (corresponding points)."""
    pts = np.asarray(pts, dtype=np.float64)
    return float(np.linalg.norm(_transform(pts, R_est, t_est) - _transform(pts, R_gt, t_gt), axis=1).mean())


def adi(R_est, t_est, R_gt, t_gt, pts) -> float:  # noqa: ANN001
    """Average distance to the nearest model point (ADD-S, for symmetric objects)."""
    pts = np.asarray(pts, dtype=np.float64)
    e, g = _transform(pts, R_est, t_est), _transform(pts, R_gt, t_gt)
    nearest = [
        np.sqrt(((g[i : i + 1024, None, :] - e[None, :, :]) ** 2).sum(-1).min(1))
        for i in range(0, len(g), 1024)
    ]
    return float(np.concatenate(nearest).mean())


def re(R_est, R_gt) -> float:  # noqa: ANN001
    """Rotation error: the angle of ``R_est R_gtᵀ``, degrees."""
    c = (np.trace(np.asarray(R_est, dtype=np.float64) @ np.asarray(R_gt, dtype=np.float64).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def te(t_est, t_gt) -> float:  # noqa: ANN001
    """Translation error ``‖t_est − t_gt‖``."""
    return float(
        np.linalg.norm(
            np.asarray(t_est, dtype=np.float64).reshape(3) - np.asarray(t_gt, dtype=np.float64).reshape(3)
        )
    )


__all__ = ["add", "adi", "depth_to_distance", "mspd", "mssd", "re", "symmetry_transforms", "te", "vsd"]
