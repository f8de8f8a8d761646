"""Headless Mollweide SO(3) plots and translation scatter; atomic figure saving.

The plots use ``matplotlib.figure.Figure`` directly (no pyplot), so no backend needs selecting."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from torch.testing import assert_close

from posediff.lie import SO3
from posediff.symmetry import equivalent_rotations
from posediff.viz import plot_so3, plot_translations, rotation_to_mollweide, save_figure

F64 = torch.float64
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _rot(axis: int, angle: float) -> torch.Tensor:
    phi = torch.zeros(3, dtype=F64)
    phi[axis] = angle
    return SO3().exp(phi)


def test_rotation_to_mollweide_convention() -> None:
    lon, lat, roll = 0.7, 0.4, -1.1
    R = _rot(2, lon) @ _rot(1, -lat) @ _rot(0, roll)  # R = Rz(lon)·Ry(−lat)·Rx(roll)
    out = rotation_to_mollweide(torch.stack([torch.eye(3, dtype=F64), R]))
    assert_close(
        torch.as_tensor(np.stack(out)), torch.tensor([[0.0, lon], [0.0, lat], [0.0, roll]], dtype=F64)
    )
    # the position is the direction of the rotated x-axis
    d = R[:, 0]
    assert math.isclose(out[0][1], math.atan2(d[1], d[0])) and math.isclose(out[1][1], math.asin(d[2]))


def _png_ok(path: Path) -> None:
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert [p.name for p in path.parent.iterdir() if p.name.endswith(".tmp")] == []


def test_plot_so3_torch_with_gt_and_save(tmp_path: Path) -> None:
    gen = torch.Generator().manual_seed(0)
    R_gt = SO3().sample_uniform((), generator=gen, dtype=F64)
    eq = equivalent_rotations("cube", R_gt)
    samples = eq.repeat(10, 1, 1) @ SO3().exp(0.05 * torch.randn(240, 3, generator=gen, dtype=F64))
    ax = plot_so3(samples, gt=eq, title="cube")
    assert ax.name == "mollweide" and ax.get_title() == "cube"
    out = save_figure(ax, tmp_path / "sub" / "so3.png")
    _png_ok(out)


def test_plot_so3_numpy_weights_given_axes(tmp_path: Path) -> None:
    fig = Figure(figsize=(6, 3))
    ax = fig.add_subplot(111, projection="mollweide")
    R = SO3().sample_uniform((100,), generator=torch.Generator().manual_seed(1), dtype=F64).numpy()
    assert plot_so3(R, ax=ax, weights=np.linspace(0.0, 1.0, 100), gt=R[0], colorwheel=False) is ax
    path = tmp_path / "w.png"
    path.write_bytes(b"old")  # overwritten atomically
    save_figure(fig, path)
    _png_ok(path)
    with pytest.raises(ValueError):
        plot_so3(R, ax=Figure().add_subplot(111))
    with pytest.raises(ValueError):
        plot_so3(R, weights=np.ones(3))


def test_plot_translations(tmp_path: Path) -> None:
    t = torch.randn(200, 3, generator=torch.Generator().manual_seed(2))
    ax = plot_translations(t, gt=torch.zeros(3), title="t")
    assert ax.name == "3d"
    _png_ok(save_figure(ax.figure, tmp_path / "t3d.png"))
    ax2 = plot_translations(
        t.numpy(), ax=Figure().add_subplot(111), gt=np.zeros((2, 3)), weights=np.ones(200)
    )
    assert ax2.name == "rectilinear"
    _png_ok(save_figure(ax2, tmp_path / "t2d.png"))
