"""Distribution metrics: spread, translation error, mode coverage, recall."""

import math
import time

import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.lie import SO3
from posediff.metrics import mode_coverage, recall, rotation_spread_deg, translation_error
from posediff.symmetry import SHAPES, equivalent_rotations, symmetry_group

F64 = torch.float64
DISCRETE = ("tet", "cube", "icosa")


def _rand_rot(shape: tuple[int, ...], seed: int) -> Tensor:
    return SO3().sample_uniform(shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


def _random_axes(shape: tuple[int, ...], seed: int) -> Tensor:
    a = torch.randn(*shape, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return a / a.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("shape", SHAPES)
def test_spread_of_exact_equivalents_is_zero(shape: str) -> None:
    R_gt = _rand_rot((3,), 0)
    samples = equivalent_rotations(shape, R_gt)
    spread = rotation_spread_deg(shape, samples, R_gt)
    assert spread.shape == (3,)
    assert_close(spread, torch.zeros(3, dtype=F64), atol=1e-5, rtol=0)


@pytest.mark.parametrize("shape", SHAPES)
def test_spread_of_small_offset_is_that_angle(shape: str) -> None:
    """R_gt·S·Exp(δ a): for the polyhedra any axis works (other modes are ≥ 72° − δ away); for
    cone / cylinder a tilt about x (⊥ the symmetry axis) is provably δ from the nearest equivalent:
    tr(Rz(γ)Rx(δ)) = cos γ (1 + cos δ) + cos δ is largest at γ = 0."""
    B, N = 4, 50
    delta = math.radians(3.0)
    R_gt = _rand_rot((B,), 1)
    if shape in DISCRETE:
        G = symmetry_group(shape)
        S = G[torch.randint(len(G), (B, N), generator=torch.Generator().manual_seed(2))]
        axes = _random_axes((B, N), 3)
    else:
        alpha = torch.rand(B, N, generator=torch.Generator().manual_seed(2), dtype=F64) * 2 * math.pi
        S = SO3().exp(torch.stack([torch.zeros_like(alpha), torch.zeros_like(alpha), alpha], dim=-1))
        axes = torch.tensor([1.0, 0.0, 0.0], dtype=F64).expand(B, N, 3)
    samples = R_gt[:, None] @ S @ SO3().exp(delta * axes)
    assert_close(rotation_spread_deg(shape, samples, R_gt), torch.full((B,), 3.0, dtype=F64))


def test_spread_float32_and_broadcast() -> None:
    R_gt = _rand_rot((2,), 4).float()
    samples = R_gt[:, None].expand(2, 5, 3, 3)
    spread = rotation_spread_deg("icosa", samples, R_gt)
    assert spread.dtype == torch.float32 and spread.abs().max() < 0.1


def test_translation_error() -> None:
    t_gt = torch.randn(3, 3, generator=torch.Generator().manual_seed(5), dtype=F64)
    d = torch.tensor([0.1, 0.5, 2.0], dtype=F64)
    t = t_gt[:, None] + d[:, None, None] * _random_axes((3, 7), 6)
    assert_close(translation_error(t, t_gt), d)


@pytest.mark.parametrize("shape", DISCRETE)
def test_mode_coverage(shape: str) -> None:
    B = 3
    R_gt = _rand_rot((B,), 7)
    E = equivalent_rotations(shape, R_gt)  # (B, S, 3, 3)
    S = E.shape[1]
    assert_close(mode_coverage(shape, E, R_gt), torch.ones(B, dtype=F64))
    # every mode hit by several noisy samples (2° < 5°)
    noisy = E.repeat(1, 3, 1, 1) @ SO3().exp(math.radians(2.0) * _random_axes((B, 3 * S), 8))
    assert_close(mode_coverage(shape, noisy, R_gt), torch.ones(B, dtype=F64))
    # half of the modes, each hit twice
    half = E[:, : S // 2].repeat(1, 2, 1, 1)
    assert_close(mode_coverage(shape, half, R_gt), torch.full((B,), 0.5, dtype=F64))
    # samples 10° away from every mode cover nothing at 5°, everything at 15°
    far = E @ SO3().exp(math.radians(10.0) * _random_axes((B, S), 9))
    assert_close(mode_coverage(shape, far, R_gt), torch.zeros(B, dtype=F64))
    assert_close(mode_coverage(shape, far, R_gt, threshold_deg=15.0), torch.ones(B, dtype=F64))


@pytest.mark.parametrize("shape", ["cone", "cyl"])
def test_mode_coverage_continuous_is_nan(shape: str) -> None:
    R_gt = _rand_rot((4,), 10)
    cov = mode_coverage(shape, R_gt[:, None].expand(4, 6, 3, 3), R_gt)
    assert cov.shape == (4,) and cov.isnan().all()


def test_recall() -> None:
    errors = torch.tensor([1.0, 2.0, 3.0, 4.0, float("nan")])
    assert_close(recall(errors, [2.0, 2.5, 4.0, 5.0]), torch.tensor([0.2, 0.4, 0.6, 0.8]))
    assert_close(recall(errors.reshape(5, 1), torch.tensor([10.0])), torch.tensor([0.8]))
    assert recall(torch.tensor([]), [1.0, 2.0]).isnan().all()
    assert_close(recall(torch.tensor([1, 3]), [2]), torch.tensor([0.5], dtype=F64))


def test_large_batch_is_vectorised() -> None:
    """B = 8, N = 1000, S = 60: one (B, N, S) trace tensor; well under a second."""
    R_gt = _rand_rot((8,), 11).float()
    samples = _rand_rot((8, 1000), 12).float()
    start = time.perf_counter()
    spread = rotation_spread_deg("icosa", samples, R_gt)
    cov = mode_coverage("icosa", samples, R_gt)
    elapsed = time.perf_counter() - start
    assert spread.shape == cov.shape == (8,)
    # uniform samples: the mean min angle to 60 modes is well below the uniform mean (~126°)
    assert 20.0 < spread.min() and spread.max() < 60.0
    assert elapsed < 5.0


def test_per_sample_errors_average_to_spread_and_translation_error() -> None:
    from posediff.metrics import rotation_errors_deg, translation_errors

    g = torch.Generator().manual_seed(5)
    R = SO3().sample_uniform((2, 7), generator=g, dtype=torch.float64)
    R_gt = SO3().sample_uniform((2,), generator=g, dtype=torch.float64)
    err = rotation_errors_deg("cube", R, R_gt)
    assert err.shape == (2, 7) and float(err.max()) <= 62.8 + 1e-6  # the cube's covering radius
    torch.testing.assert_close(err.mean(-1), rotation_spread_deg("cube", R, R_gt))
    t = torch.randn(2, 7, 3, generator=g, dtype=torch.float64)
    t_gt = torch.randn(2, 3, generator=g, dtype=torch.float64)
    d = translation_errors(t, t_gt)
    torch.testing.assert_close(d[1, 3], (t[1, 3] - t_gt[1]).norm())
    torch.testing.assert_close(d.mean(-1), translation_error(t, t_gt))
