"""A picture of the data: the five shapes of SYMSOL-T (or SYMSOL) in a grid, one row per shape."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...symmetry import SHAPES
from .poses import sample_poses
from .render import SCENE_DISTANCE, SymsolRenderer


def render_grid(
    path: str | os.PathLike[str],
    *,
    dataset: str = "symsolt",
    variant: str | None = None,
    per_shape: int = 4,
    image_size: int = 224,
    seed: int = 0,
) -> Path:
    """Render ``per_shape`` test-split poses of every shape (rows: tet, cube, icosa, cone, cyl) and
    save the grid as an image at ``path`` (atomically; the format follows the suffix)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...viz import save_figure

    renderer = SymsolRenderer(image_size)
    fig, axes = plt.subplots(
        len(SHAPES), per_shape, figsize=(1.6 * per_shape, 1.6 * len(SHAPES)), squeeze=False
    )
    for row, shape in enumerate(SHAPES):
        poses = sample_poses(dataset, variant, "test", per_shape, seed, shapes=[shape])
        for col in range(per_shape):
            out = renderer.render(shape, poses.R[col], poses.t[col])
            ax = axes[row, col]
            ax.imshow(out.rgb)
            ax.set_xticks([])
            ax.set_yticks([])
            t = poses.t[col] - np.array([0.0, 0.0, SCENE_DISTANCE])
            ax.set_title(f"t=({t[0]:+.1f},{t[1]:+.1f},{t[2]:+.1f})", fontsize=6, pad=2)
            if col == 0:
                ax.set_ylabel(shape, fontsize=9)
    fig.subplots_adjust(wspace=0.04, hspace=0.22)
    saved = save_figure(fig, path, dpi=110)
    plt.close(fig)
    renderer.close()
    return saved


__all__ = ["render_grid"]
