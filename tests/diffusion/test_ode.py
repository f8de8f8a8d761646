"""The probability-flow ODE samplers: convergence order on the group, σ grids, NFE accounting, options."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import (
    ConcentratedGaussian,
    CrouchGrossmanSampler,
    Diffusion,
    FewStepSampler,
    GeodesicRandomWalk,
    HeunSampler,
    LinearSchedule,
    MixtureOracle,
    PowerSchedule,
    RKMKSampler,
)
from posediff.lie import get_group
from posediff.symmetry import symmetry_group

F64 = torch.float64


def _setup(group: str) -> tuple[Diffusion, MixtureOracle]:
    g = get_group(group)
    d = Diffusion(ConcentratedGaussian(g), LinearSchedule(), prior="haar")
    modes = symmetry_group("tet", dtype=F64)[:4]
    if g.matrix_dim == 4:
        t = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.4, -0.3], [-0.2, 0.1, 0.2], [0.1, 0.1, -0.1]], dtype=F64)
        modes = torch.cat(
            [torch.cat([modes, t.unsqueeze(-1)], -1), torch.eye(4, dtype=F64)[3:].expand(4, 1, 4)], -2
        )
    return d, MixtureOracle(d, modes, torch.tensor([0.4, 0.3, 0.2, 0.1], dtype=F64))


def _integrate(sampler, oracle, x0: torch.Tensor, n: int) -> torch.Tensor:  # noqa: ANN001
    sig = torch.linspace(0.6, 0.1, n + 1, dtype=F64).tolist()
    x = x0
    for a, b in zip(sig[:-1], sig[1:], strict=True):
        x = sampler.ode_step(oracle, x, a, b - a, None)
    return x


@pytest.mark.parametrize("group", ["so3", "se3"])
@pytest.mark.parametrize(
    ("cls", "order", "ns"),
    [(HeunSampler, 2, (8, 16, 32)), (CrouchGrossmanSampler, 3, (16, 32, 64)), (RKMKSampler, 4, (8, 16, 32))],
)
def test_convergence_order_on_the_group(group: str, cls: type, order: int, ns: tuple[int, ...]) -> None:
    """Halving the step divides the global error by about 2^order (σ 0.6 → 0.1 with the exact score of a
    4-mode mixture; reference: RKMK with 400 steps; the first halving may be pre-asymptotic)."""
    d, oracle = _setup(group)
    g = d.group
    x0 = g.sample_uniform((1, 32), generator=torch.Generator().manual_seed(0), dtype=F64, bound=1.0)
    ref = _integrate(RKMKSampler(d), oracle, x0, 400)
    errs = [float(g.rminus(ref, _integrate(cls(d), oracle, x0, n)).norm(dim=-1).max()) for n in ns]
    rates = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert rates[0] > order - 1.25 and rates[1] > order - 0.5, (errs, rates)


def test_sigma_grids() -> None:
    d = Diffusion(ConcentratedGaussian("so3"), PowerSchedule(), prior="haar")
    sched = d.schedule
    t, p = HeunSampler(d).sigma_grid(7)
    ref_t, ref_p = FewStepSampler(d).sigma_grid(7)
    assert torch.equal(t, ref_t) and torch.equal(p, ref_p)
    for spacing in ("karras", "loglinear"):
        t, p = HeunSampler(d, spacing=spacing).sigma_grid(6)
        assert t.shape == (6,) and float(t[0]) == sched.sigma_max and float(t[-1]) == sched.sigma_min
        assert bool((t[1:] < t[:-1]).all()) and torch.equal(p[:-1], t[1:]) and float(p[-1]) == 0.0
    # Karras ρ = 7 puts more steps near the data than the geometric grid's half-way point
    k, _ = HeunSampler(d, spacing="karras").sigma_grid(6)
    lg, _ = HeunSampler(d, spacing="loglinear").sigma_grid(6)
    assert float(k[2]) > float(lg[2])
    r = 1 / 7
    assert_close(
        k[1],
        torch.tensor((sched.sigma_max**r + 0.2 * (sched.sigma_min**r - sched.sigma_max**r)) ** 7, dtype=F64),
    )
    one, nxt = HeunSampler(d, spacing="karras").sigma_grid(1)
    assert one.tolist() == [sched.sigma_max] and nxt.tolist() == [0.0]


def test_nfe_accounting() -> None:
    d = Diffusion(ConcentratedGaussian("so3"), LinearSchedule(), prior="haar")
    for sampler, five, hundred in (
        (FewStepSampler(d), 5, 100),
        (FewStepSampler(d, order=2), 3, 50),
        (HeunSampler(d), 3, 50),
        (CrouchGrossmanSampler(d), 2, 34),
        (RKMKSampler(d), 2, 25),
        (GeodesicRandomWalk(d), 5, 100),
    ):
        assert sampler.steps_for_nfe(5) == five, type(sampler).__name__
        assert sampler.steps_for_nfe(100) == hundred, type(sampler).__name__
        assert sampler.network_calls(sampler.steps_for_nfe(100)) <= 100
    assert RKMKSampler(d).steps_for_nfe(1) == 1 and RKMKSampler(d).network_calls(1) == 1


def test_one_step_is_the_clean_prediction_from_the_prior() -> None:
    """At one step every ODE sampler is X · Exp(σ_max² s) — the few_step sampler's one step."""
    d, oracle = _setup("se3")
    base = FewStepSampler(d).sample(oracle, None, 16, 1, torch.Generator().manual_seed(3), dtype=F64)
    for cls in (HeunSampler, CrouchGrossmanSampler, RKMKSampler):
        x = cls(d).sample(oracle, None, 16, 1, torch.Generator().manual_seed(3), dtype=F64)
        assert_close(x, base)


def test_invalid_options() -> None:
    d = Diffusion(ConcentratedGaussian("so3"), LinearSchedule(), prior="haar")
    with pytest.raises(ValueError, match="unknown spacing 'edm'; options: schedule, karras, loglinear"):
        HeunSampler(d, spacing="edm")
    with pytest.raises(ValueError, match="rho must be > 0"):
        RKMKSampler(d, rho=0.0)
    with pytest.raises(ValueError, match=r"num_steps must be a whole number in \[1, 100\]"):
        CrouchGrossmanSampler(d, num_steps=0)
