"""The pictures of a prediction, over plain arrays (``posediff predict`` writes them through
:func:`posediff.evaluation.predict.save_prediction`): the Mollweide SO(3) plot of hypotheses and
modes, the sampled translations, the top modes drawn over the input, the denoising trajectory."""

from __future__ import annotations

from typing import Any

import numpy as np

from .mollweide import plot_so3


def _rotations(poses: Any) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    return P[..., :3, :3]


def figure_so3(
    samples: Any,
    mode_poses: Any = None,
    mode_weights: Any = None,
    *,
    gt_rotations: np.ndarray | None = None,
    title: str = "",
) -> Any:
    """Hypotheses ``(N, n, n)`` (rotations or poses) as dots, modes ``(K, n, n)`` as discs sized by
    ``mode_weights (K,)``, the ground truth's equivalent rotations ``(E, 3, 3)`` as circles."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 4.8))
    ax = fig.add_subplot(1, 1, 1, projection="mollweide")
    R = _rotations(samples)
    plot_so3(R, ax=ax, gt=gt_rotations, title=title or f"{len(R)} hypotheses")
    if mode_poses is not None and len(mode_poses):
        plot_so3(
            _rotations(mode_poses), ax=ax, weights=np.asarray(mode_weights), marker_size=160, colorwheel=False
        )
    return fig


def figure_translations(translations: Any, gt_translation: np.ndarray | None = None) -> Any:
    """x–y and x–z scatters of sampled translations ``(N, 3)``."""
    from matplotlib.figure import Figure

    t = np.asarray(translations, dtype=np.float64)
    fig = Figure(figsize=(9, 4.3))
    for k, (i, j) in enumerate(((0, 1), (0, 2))):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.scatter(t[:, i], t[:, j], s=4, alpha=0.5, label="hypotheses")
        if gt_translation is not None:
            ax.scatter(
                [gt_translation[i]], [gt_translation[j]], marker="x", s=80, c="red", label="ground truth"
            )
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.legend(loc="best", fontsize=8)
    fig.suptitle("sampled translations")
    return fig


def mesh_edges(mesh: Any, sharp_deg: float = 20.0) -> tuple[np.ndarray, float]:
    """``(edges (E, 2, 3), axis_length)``: the feature edges of a trimesh (faces meeting at more than
    ``sharp_deg``), and half the model's largest extent."""
    mesh = mesh.copy()
    mesh.merge_vertices()  # BOP models split vertices at sharp edges; adjacency needs them shared
    sharp = mesh.face_adjacency_angles > np.radians(sharp_deg)
    edges = np.asarray(mesh.vertices)[mesh.face_adjacency_edges[sharp]]
    return edges, 0.5 * float(np.ptp(np.asarray(mesh.vertices), axis=0).max())


def overlay(
    image: Any,
    poses: Any,
    K: np.ndarray,
    *,
    edges: np.ndarray | None = None,
    axis_length: float = 1.0,
    camera_offset: np.ndarray | None = None,
    scale: int = 4,
) -> np.ndarray:
    """The input — ``(3, S, S)`` floats in [0, 1] or ``(S, S, 3)`` uint8 — upscaled ``scale``× with each
    pose of ``poses (K, n, n)`` drawn over it: the wire-frame ``edges (E, 2, 3)`` (model frame), else
    coordinate axes of ``axis_length``. ``camera_offset`` is added to the translation to get the
    camera-frame one; rotation-only poses are drawn at the offset. Returns ``(S·scale, S·scale, 3)``
    uint8 RGB."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[0] == 3 and img.dtype != np.uint8:
        img = (np.transpose(img, (1, 2, 0)) * 255).clip(0, 255).astype(np.uint8)
    img = cv2.resize(np.ascontiguousarray(img), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    Ks = np.asarray(K, dtype=np.float64).copy()
    Ks[:2] *= scale
    Ks[:2, 2] += (scale - 1) / 2.0  # pixel centres stay put when upscaling
    P = np.asarray(poses, dtype=np.float64)
    R, t = P[..., :3, :3], (P[..., :3, 3] if P.shape[-1] == 4 else None)
    off = np.zeros(3) if camera_offset is None else np.asarray(camera_offset, dtype=np.float64)
    colours = [(255, 80, 80), (80, 255, 80), (80, 160, 255), (255, 220, 60), (255, 80, 255)]
    for k in range(len(R)):
        tk = off + (t[k] if t is not None else 0.0)
        rvec, _ = cv2.Rodrigues(R[k])
        colour = colours[k % len(colours)]
        if edges is not None and len(edges):
            pts, _ = cv2.projectPoints(np.asarray(edges).reshape(-1, 3), rvec, tk, Ks, None)
            for a, b in pts.reshape(-1, 2, 2):
                cv2.line(
                    img,
                    tuple(int(round(v)) for v in a),
                    tuple(int(round(v)) for v in b),
                    colour,
                    1,
                    cv2.LINE_AA,
                )
        else:
            cv2.drawFrameAxes(img, Ks, None, rvec, tk, axis_length, 2)
    return img


def figure_trajectory(trajectory: Any, panels: int = 5, gt_rotations: np.ndarray | None = None) -> Any:
    """The samples of a trajectory ``(T+1, N, n, n)`` at ``panels`` evenly spaced levels (prior →
    result), the ground truth on the last."""
    from matplotlib.figure import Figure

    traj = np.asarray(trajectory, dtype=np.float64)
    T = traj.shape[0] - 1
    steps = sorted({round(i * T / (panels - 1)) for i in range(panels)})
    fig = Figure(figsize=(4.2 * len(steps), 2.8))
    for k, s in enumerate(steps):
        ax = fig.add_subplot(1, len(steps), k + 1, projection="mollweide")
        plot_so3(_rotations(traj[s]), ax=ax, gt=gt_rotations if s == T else None,
                 title="prior" if s == 0 else f"step {s}/{T}", colorwheel=False, marker_size=3)  # fmt: skip
    return fig


__all__ = ["figure_so3", "figure_trajectory", "figure_translations", "mesh_edges", "overlay"]
