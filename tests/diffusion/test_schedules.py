"""Noise schedules: the authors' power table, linear / log-linear spacing, timesteps, level inversion."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import LinearSchedule, LogLinearSchedule, NoiseSchedule, PowerSchedule

# reference-implementation.md §3.2 (the authors' code, T = 100, a0 = 1e-8, a1 = 1, p = 3)
AUTHORS_TABLE = {
    0: 1.0e-4,
    1: 1.336e-3,
    2: 3.288e-3,
    5: 0.011874,
    10: 0.032547,
    25: 0.12621,
    50: 0.3547,
    75: 0.65022,
    90: 0.85412,
    98: 0.97021,
    99: 0.98507,
}

SCHEDULES = [PowerSchedule, LinearSchedule, LogLinearSchedule]


def _round_sig(x: float, digits: int = 4) -> float:
    return float(f"{x:.{digits - 1}e}")


def test_power_schedule_matches_the_authors_table() -> None:
    sched = PowerSchedule()
    assert sched.num_levels == 100
    sig = sched.sigmas
    assert sig.dtype == torch.float64 and sig.shape == (100,)
    for i, ref in AUTHORS_TABLE.items():
        assert _round_sig(float(sig[i])) == _round_sig(ref), (i, float(sig[i]), ref)
    assert sched.sigma_min == pytest.approx(1e-4, rel=1e-12)
    assert sched.sigma_max == pytest.approx(0.98507, abs=5e-6)


def test_power_schedule_closed_form() -> None:
    """σ_i = (c0 + (1 − c0)·i/T)^{3/2}, c0 = 1e-8^{1/3} (reference §3.2), written independently."""
    c0 = 1e-8 ** (1 / 3)
    expected = torch.tensor([(c0 + (1 - c0) * i / 100) ** 1.5 for i in range(100)], dtype=torch.float64)
    assert_close(PowerSchedule().sigmas, expected, rtol=1e-12, atol=0)


def test_linear_schedule_endpoints_and_spacing() -> None:
    sig = LinearSchedule().sigmas
    assert sig.shape == (100,)
    assert float(sig[0]) == pytest.approx(1e-4, rel=1e-12)
    assert float(sig[-1]) == pytest.approx(1.0, rel=1e-12)
    step = sig.diff()
    assert_close(step, torch.full_like(step, (1.0 - 1e-4) / 99), rtol=1e-9, atol=0)


def test_loglinear_schedule_is_geometric() -> None:
    sched = LogLinearSchedule(num_levels=50, sigma_min=1e-3, sigma_max=2.0)
    sig = sched.sigmas
    assert sched.sigma_min == pytest.approx(1e-3, rel=1e-10)
    assert sched.sigma_max == pytest.approx(2.0, rel=1e-10)
    ratio = sig[1:] / sig[:-1]
    assert_close(ratio, torch.full_like(ratio, (2.0 / 1e-3) ** (1 / 49)), rtol=1e-10, atol=0)


def test_sigmas_is_a_copy() -> None:
    sched = PowerSchedule()
    sched.sigmas[0] = 123.0
    assert sched.sigma_min == pytest.approx(1e-4)


@pytest.mark.parametrize("cls", SCHEDULES)
@pytest.mark.parametrize("n", [1, 2, 5, 10, 50, 99, 100])
def test_timesteps(cls: type[NoiseSchedule], n: int) -> None:
    sched = cls()
    t = sched.timesteps(n)
    assert t.dtype == torch.long and t.shape == (n,)
    assert int(t[0]) == 99
    if n >= 2:
        assert int(t[-1]) == 0
        assert bool((t[1:] < t[:-1]).all())  # strictly descending, hence unique
    assert len(set(t.tolist())) == n
    assert bool(((t >= 0) & (t <= 99)).all())


def test_timesteps_default_is_every_level_and_spacing_is_even() -> None:
    sched = PowerSchedule()
    assert sched.timesteps().tolist() == list(range(99, -1, -1))
    gaps = -sched.timesteps(10).diff()
    assert int(gaps.min()) >= 10 and int(gaps.max()) <= 12


@pytest.mark.parametrize("n", [0, -1, 101])
def test_timesteps_out_of_range(n: int) -> None:
    with pytest.raises(ValueError, match=r"num_steps must be in \[1, 100\]"):
        PowerSchedule().timesteps(n)


def test_timesteps_small_schedule() -> None:
    sched = LinearSchedule(num_levels=4)
    assert sched.timesteps(4).tolist() == [3, 2, 1, 0]
    assert sched.timesteps(2).tolist() == [3, 0]
    with pytest.raises(ValueError):
        sched.timesteps(5)


@pytest.mark.parametrize("cls", SCHEDULES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_level_inverts_sigma(cls: type[NoiseSchedule], dtype: torch.dtype) -> None:
    sched = cls()
    levels = torch.arange(100)
    sig = sched.sigma(levels, dtype=dtype)
    assert sig.dtype == dtype
    lev = sched.level(sig)
    assert lev.dtype == dtype
    assert_close(lev.double(), levels.double(), rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-9)


@pytest.mark.parametrize("cls", SCHEDULES)
def test_level_is_monotone_between_levels(cls: type[NoiseSchedule]) -> None:
    sched = cls()
    sig = sched.sigmas
    mid = (sig[1:] * sig[:-1]).sqrt()  # geometric midpoints: level is linear in log σ
    lev_mid = sched.level(mid)
    assert_close(lev_mid, torch.arange(99, dtype=torch.float64) + 0.5, rtol=0, atol=1e-9)
    grid = torch.logspace(math.log10(sched.sigma_min), math.log10(sched.sigma_max), 5000, dtype=torch.float64)
    lev = sched.level(grid)
    assert bool((lev.diff() >= 0).all())
    assert float(lev[0]) == pytest.approx(0.0, abs=1e-9) and float(lev[-1]) == pytest.approx(99.0, abs=1e-9)
    # clamped outside the table
    out = sched.level(torch.tensor([sched.sigma_min / 10, sched.sigma_max * 10], dtype=torch.float64))
    assert out.tolist() == [0.0, 99.0]


def test_level_keeps_shape() -> None:
    sched = PowerSchedule()
    sig = sched.sigma(torch.tensor([[3, 7, 0], [99, 50, 1]]), dtype=torch.float64)
    assert sched.level(sig).shape == (2, 3)


def test_sample_levels_covers_every_level() -> None:
    sched = PowerSchedule()
    gen = torch.Generator().manual_seed(0)
    lv = sched.sample_levels((50, 200), generator=gen)
    assert lv.shape == (50, 200) and lv.dtype == torch.long
    assert int(lv.min()) == 0 and int(lv.max()) == 99
    counts = torch.bincount(lv.flatten(), minlength=100)
    assert counts.shape == (100,) and int(counts.min()) > 50  # ≈ 100 per level
    again = sched.sample_levels((50, 200), generator=torch.Generator().manual_seed(0))
    assert torch.equal(lv, again)


def test_invalid_schedules() -> None:
    with pytest.raises(ValueError, match="num_levels"):
        PowerSchedule(num_levels=1)
    with pytest.raises(ValueError, match="increasing"):
        LinearSchedule(sigma_min=1.0, sigma_max=0.5)
