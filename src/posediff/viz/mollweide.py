"""Implicit-PDF-style plots of rotation distributions (Murphy et al. 2021), headless-safe.

Convention for :func:`plot_so3`: a rotation R is decomposed as ``R = Rz(lon)·Ry(−lat)·Rx(roll)``.
The point is drawn on a Mollweide map at the direction of the rotated x-axis ``d = R e_x``
(longitude ``lon = atan2(d_y, d_x)``, latitude ``lat = asin(d_z)``) and coloured by ``roll``
(the rotation about that axis, ``atan2(R21, R22)``) through a cyclic colormap over [−π, π).
The decomposition is singular only for d = ±e_z (measure zero). Ground-truth rotations are
unfilled circles with the same position and colour convention.

Figures are built with :class:`matplotlib.figure.Figure` directly (no pyplot, no global state,
works with any backend including Agg). Inputs may be torch tensors or numpy arrays.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any

import matplotlib as mpl
import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

_ROLL_NORM = Normalize(vmin=-np.pi, vmax=np.pi)


def _to_numpy(x: Any) -> np.ndarray:
    """torch tensor / array-like → float64 numpy array (detached, on the CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def rotation_to_mollweide(rotations: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(…, 3, 3)`` rotations → ``(lon, lat, roll)`` arrays (radians) with
    ``R = Rz(lon)·Ry(−lat)·Rx(roll)``: lon ∈ (−π, π], lat ∈ [−π/2, π/2], roll ∈ (−π, π]."""
    R = _to_numpy(rotations)
    lon = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    lat = np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return lon, lat, roll


def _new_axes(projection: str | None, figsize: tuple[float, float]) -> Axes:
    fig = Figure(figsize=figsize)
    return fig.add_subplot(111, projection=projection)


def _add_roll_wheel(ax: Axes, cmap: Any) -> Axes:
    """A small colour ring in the lower right corner of ``ax`` explaining the roll colours."""
    wax = ax.inset_axes([0.86, -0.02, 0.17, 0.17], projection="polar")
    theta = np.linspace(-np.pi, np.pi, 181)
    radius = np.array([0.55, 1.0])
    T, Rr = np.meshgrid(theta, radius)
    C = 0.5 * (theta[:-1] + theta[1:])[None, :]
    wax.pcolormesh(T, Rr, C, cmap=cmap, norm=_ROLL_NORM, shading="flat")
    wax.set_ylim(0.0, 1.0)
    wax.set_yticks([])
    wax.set_xticks([0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi])
    wax.set_xticklabels(["0", "90°", "±180°", "−90°"], fontsize=6)
    wax.tick_params(pad=-2)
    wax.grid(False)
    wax.set_title("roll", fontsize=7, pad=2)
    return wax


def plot_so3(
    rotations: Any,
    *,
    ax: Axes | None = None,
    gt: Any | None = None,
    weights: Any | None = None,
    title: str | None = None,
    gt_radius: float = 12.0,
    cmap: str | Any = "hsv",
    marker_size: float | None = None,
    colorwheel: bool = True,
) -> Axes:
    """Scatter ``rotations (N, 3, 3)`` on a Mollweide map (see module docstring) and return the axes.

    Args:
        ax: an axes with ``projection="mollweide"``; a new figure (8×4.5 in) is made when ``None``.
        gt: ground-truth rotations ``(G, 3, 3)`` or ``(3, 3)``, drawn as unfilled circles of radius
            ``gt_radius`` points, edge-coloured by their roll.
        weights: ``(N,)`` non-negative; marker areas are proportional to ``weights / max(weights)``
            (probability plots on a grid, as Implicit-PDF). Without weights all markers are equal.
        marker_size: marker area (points²) of unweighted points / of the largest weight
            (default 6 without weights, 200 with).
        cmap: a cyclic colormap (name or object) for the roll angle.
        colorwheel: draw a small roll colour ring.
    """
    if ax is None:
        ax = _new_axes("mollweide", (8.0, 4.5))
    elif ax.name != "mollweide":
        raise ValueError(f"plot_so3 needs an axes with projection='mollweide', got {ax.name!r}")
    cmap = mpl.colormaps[cmap] if isinstance(cmap, str) else cmap

    R = _to_numpy(rotations).reshape(-1, 3, 3)
    lon, lat, roll = rotation_to_mollweide(R)
    if weights is None:
        sizes: Any = 6.0 if marker_size is None else marker_size
    else:
        w = _to_numpy(weights).reshape(-1)
        if w.shape[0] != R.shape[0]:
            raise ValueError(f"weights has {w.shape[0]} entries for {R.shape[0]} rotations")
        top = w.max() if w.size and w.max() > 0 else 1.0
        sizes = (200.0 if marker_size is None else marker_size) * w / top
    ax.scatter(lon, lat, s=sizes, c=cmap(_ROLL_NORM(roll)), linewidths=0, zorder=2)

    if gt is not None:
        G = _to_numpy(gt).reshape(-1, 3, 3)
        glon, glat, groll = rotation_to_mollweide(G)
        ax.scatter(
            glon,
            glat,
            s=(2.0 * gt_radius) ** 2,
            facecolors="none",
            edgecolors=cmap(_ROLL_NORM(groll)),
            linewidths=2.0,
            zorder=3,
        )

    ax.grid(True)
    ax.set_xticklabels([])
    ax.tick_params(labelsize=7)
    if title is not None:
        ax.set_title(title)
    if colorwheel:
        _add_roll_wheel(ax, cmap)
    return ax


def plot_translations(
    t: Any,
    *,
    ax: Axes | None = None,
    gt: Any | None = None,
    weights: Any | None = None,
    title: str | None = None,
    marker_size: float = 6.0,
) -> Axes:
    """Scatter translations ``t (N, 3)`` and return the axes.

    With ``ax=None`` (or a 3-D axes) a 3-D scatter; with a 2-D axes the x–y projection. ``gt``
    ``(3,)`` or ``(G, 3)`` is drawn as red crosses. ``weights`` scale marker areas as in
    :func:`plot_so3`.
    """
    if ax is None:
        ax = _new_axes("3d", (6.0, 6.0))
    pts = _to_numpy(t).reshape(-1, 3)
    sizes: Any = marker_size
    if weights is not None:
        w = _to_numpy(weights).reshape(-1)
        top = w.max() if w.size and w.max() > 0 else 1.0
        sizes = marker_size * w / top
    three_d = ax.name == "3d"
    cols = (0, 1, 2) if three_d else (0, 1)
    ax.scatter(*(pts[:, k] for k in cols), s=sizes, alpha=0.6, linewidths=0, label="samples")
    if gt is not None:
        g = _to_numpy(gt).reshape(-1, 3)
        ax.scatter(
            *(g[:, k] for k in cols), s=80.0, c="red", marker="x", linewidths=2.0, label="ground truth"
        )
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if three_d:
        ax.set_zlabel("z")  # type: ignore[attr-defined]
    if title is not None:
        ax.set_title(title)
    return ax


def save_figure(fig: Figure | Axes, path: str | os.PathLike[str], **savefig_kwargs: Any) -> Path:
    """Save ``fig`` (or the figure of an axes) to ``path`` atomically: render into a temporary file
    in the same directory, then ``os.replace`` it. The format follows the suffix (default PNG);
    parent directories are created. Returns the path."""
    figure = fig.figure if isinstance(fig, Axes) else fig
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    savefig_kwargs.setdefault("format", path.suffix[1:].lower() or "png")
    savefig_kwargs.setdefault("bbox_inches", "tight")
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp"
    try:
        figure.savefig(tmp, **savefig_kwargs)
        os.replace(tmp, path)
    except OSError as e:
        from .._io import named_os_error

        raise named_os_error(e, path) from e
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
