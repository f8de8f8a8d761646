"""Contract checks for the diffusion families: kernels, score targets, schedules, samplers.

Each ``*_CHECKS`` dict maps a check name to a function that raises ``AssertionError`` on failure;
``tests/contracts/test_diffusion.py`` runs every check over every registered class, so a new
kernel / target / schedule / sampler is tested as soon as it is defined. Out-of-tree code can call
``kernel_contract(MyKernel("so3"))`` etc. directly.
"""

import functools
import math
from collections.abc import Callable
from typing import Any

import torch
from torch.testing import assert_close

from ..diffusion import (
    ConcentratedGaussian,
    Diffusion,
    FlowOracle,
    LinearSchedule,
    MixtureOracle,
    NoiseKernel,
    NoiseSchedule,
    Sampler,
    ScoreTarget,
)
from ..lie import SO3, LieGroup, get_group

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _rot_angle(g: LieGroup, x: torch.Tensor) -> torch.Tensor:
    return g.log(x)[..., g.rotation_slice].norm(dim=-1)


# ---------------------------------------------------------------------- kernels
def _kernel_sample_on_group(kernel: NoiseKernel, device: torch.device) -> None:
    g = kernel.group
    x = g.sample_uniform((64,), generator=_gen(1), dtype=F64).to(device)
    sigma = torch.linspace(0.01, 1.5, 64, dtype=F64, device=device)
    y, z = kernel.sample(x, sigma, generator=_gen(2))
    assert y.shape == x.shape and z.shape == (64, g.dim), f"sample shapes {tuple(y.shape)}, {tuple(z.shape)}"
    g.check(y)
    assert_close(y, g.rplus(x, z), msg="sample must return X·Exp(z)")
    if kernel.wrap:
        assert bool((z[..., g.rotation_slice].norm(dim=-1) <= math.pi + 1e-9).all()), (
            "wrapped z must be principal"
        )


def _kernel_determinism(kernel: NoiseKernel, device: torch.device) -> None:
    sigma = torch.full((32,), 0.3, dtype=F64, device=device)
    a = kernel.sample_tangent(sigma, generator=_gen(5))
    b = kernel.sample_tangent(sigma, generator=_gen(5))
    assert torch.equal(a, b), "the same generator seed must give the same samples"


def _kernel_small_sigma_is_gaussian(kernel: NoiseKernel, device: torch.device) -> None:
    """As σ → 0 every kernel is the tangent Gaussian N(0, σ_c²I): the covariance of z matches."""
    sigma = 0.02
    z = kernel.sample_tangent(torch.full((20000,), sigma, dtype=F64, device=device), generator=_gen(3))
    var = z.var(dim=0)
    expect = kernel.scales(dtype=F64, device=device) ** 2 * sigma**2
    assert_close(var, expect, rtol=0.06, atol=0.0, msg="small-σ variance per component")
    assert bool(z.mean(0).abs().max() < 4 * sigma / math.sqrt(20000) * 2), "small-σ mean must be ~0"


def _kernel_left_invariant(kernel: NoiseKernel, device: torch.device) -> None:
    g = kernel.group
    x = g.sample_uniform((16,), generator=_gen(6), dtype=F64).to(device)
    h = g.sample_uniform((16,), generator=_gen(7), dtype=F64).to(device)
    y, _ = kernel.sample(x, 0.4, generator=_gen(8))
    lp = kernel.log_prob(y, x, 0.4)
    lp_moved = kernel.log_prob(g.compose(h, y), g.compose(h, x), 0.4)
    assert_close(lp_moved, lp, rtol=1e-9, atol=1e-9, msg="log_prob must be left-invariant")


def _kernel_score_matches_autograd(kernel: NoiseKernel, device: torch.device) -> None:
    """The closed-form score equals the autograd gradient of log_prob through rplus (paper Eq. 18)."""
    g = kernel.group
    sigma = torch.tensor([0.1, 0.5, 1.0], dtype=F64, device=device).repeat(4)
    z = kernel.sample_tangent(sigma, generator=_gen(9))
    closed = kernel.score_tangent(z, sigma)
    auto = ScoreTarget.lookup("autograd")()(kernel, z, sigma)
    assert closed.shape == (12, g.dim)
    assert_close(closed, auto, rtol=1e-6, atol=1e-6, msg="score_tangent vs autograd of log_prob")


def _kernel_score_finite_float32(kernel: NoiseKernel, device: torch.device) -> None:
    g = kernel.group
    z = torch.zeros(3, g.dim, dtype=torch.float32, device=device)
    rot = g.rotation_slice
    z[1, rot] = torch.tensor([0.0, 0.0, math.pi - 1e-6])[: rot.stop - rot.start]
    z[2, rot] = torch.tensor([1e-7, 0.0, 0.0])[: rot.stop - rot.start]
    for sigma in (1e-4, 0.1, 1.0):
        s = kernel.score_tangent(z, sigma)
        lp = kernel.log_prob_tangent(z, sigma)
        assert bool(torch.isfinite(s).all()) and bool(torch.isfinite(lp).all()), f"non-finite at σ={sigma}"


KERNEL_CHECKS: dict[str, Callable[[NoiseKernel, torch.device], None]] = {
    "sample_on_group": _kernel_sample_on_group,
    "determinism": _kernel_determinism,
    "small_sigma_is_gaussian": _kernel_small_sigma_is_gaussian,
    "left_invariant": _kernel_left_invariant,
    "score_matches_autograd": _kernel_score_matches_autograd,
    "score_finite_float32": _kernel_score_finite_float32,
}


def kernel_groups(cls: type[NoiseKernel]) -> list[str]:
    """The registered groups a kernel class supports (what the contract runs it on)."""
    names = sorted(LieGroup.registry)
    return [n for n in names if cls.supported_groups is None or n in cls.supported_groups]


def kernel_contract(
    kernel: NoiseKernel, device: torch.device | str = "cpu", checks: list[str] | None = None
) -> None:
    _run(KERNEL_CHECKS, kernel, torch.device(device), checks)


# ---------------------------------------------------------------------- score targets
def _target_shape_and_finite(target: ScoreTarget, group: LieGroup, device: torch.device) -> None:
    kernel = ConcentratedGaussian(group)
    sigma = torch.tensor([1e-3, 0.1, 1.0], dtype=F64, device=device)
    z = kernel.sample_tangent(sigma, generator=_gen(11))
    s = target(kernel, z, sigma)
    assert s.shape == z.shape and s.dtype == z.dtype, f"target shape {tuple(s.shape)} vs {tuple(z.shape)}"
    assert bool(torch.isfinite(s).all())


def _target_equals_surrogate_where_jacobians_commute(
    target: ScoreTarget, group: LieGroup, device: torch.device
) -> None:
    """Paper Eq. 8–10: on SO3 and R3SO3 (J_l = J_rᵀ) every Gaussian score target is −z/σ²."""
    if group.name not in ("so3", "r3so3"):
        return
    kernel = ConcentratedGaussian(group)
    sigma = torch.tensor([0.05, 0.3, 0.9], dtype=F64, device=device).repeat(5)
    z = kernel.sample_tangent(sigma, generator=_gen(12))
    assert_close(target(kernel, z, sigma), -z / sigma.unsqueeze(-1) ** 2, rtol=1e-7, atol=1e-7)


def _target_small_noise_limit(target: ScoreTarget, group: LieGroup, device: torch.device) -> None:
    """Every target is −z/σ² to first order as z → 0 (all groups)."""
    kernel = ConcentratedGaussian(group)
    z = 1e-6 * torch.randn(8, group.dim, generator=_gen(13), dtype=F64).to(device)
    sigma = 0.01
    assert_close(target(kernel, z, sigma) * sigma**2, -z, rtol=1e-5, atol=1e-12)


SCORE_TARGET_CHECKS: dict[str, Callable[[ScoreTarget, LieGroup, torch.device], None]] = {
    "shape_and_finite": _target_shape_and_finite,
    "equals_surrogate_on_so3_r3so3": _target_equals_surrogate_where_jacobians_commute,
    "small_noise_limit": _target_small_noise_limit,
}


def score_target_contract(
    target: ScoreTarget,
    group: LieGroup | str = "so3",
    device: torch.device | str = "cpu",
    checks: list[str] | None = None,
) -> None:
    g = get_group(group) if isinstance(group, str) else group
    names = list(SCORE_TARGET_CHECKS) if checks is None else checks
    for name in names:
        SCORE_TARGET_CHECKS[name](target, g, torch.device(device))


# ---------------------------------------------------------------------- schedules
def _schedule_levels(schedule: NoiseSchedule) -> None:
    s = schedule.sigmas
    assert s.dtype == F64 and s.ndim == 1 and len(s) == schedule.num_levels
    assert bool((s > 0).all()) and bool((s[1:] > s[:-1]).all()), "σ must be positive and increasing"
    assert schedule.sigma_min == float(s[0]) and schedule.sigma_max == float(s[-1])


def _schedule_timesteps(schedule: NoiseSchedule) -> None:
    L = schedule.num_levels
    for n in sorted({1, 2, 5, min(10, L), L}):
        t = schedule.timesteps(n)
        assert t.dtype == torch.long and t.shape == (n,), f"timesteps({n}) shape {tuple(t.shape)}"
        assert int(t[0]) == L - 1, "sampling starts at the top level"
        if n > 1:
            assert int(t[-1]) == 0 and bool((t[1:] < t[:-1]).all()), "strictly descending to level 0"
    assert torch.equal(schedule.timesteps(None), torch.arange(L - 1, -1, -1))
    for bad in (0, L + 1):
        try:
            schedule.timesteps(bad)
        except ValueError:
            continue
        raise AssertionError(f"timesteps({bad}) must raise ValueError")


def _schedule_level_inverts_sigma(schedule: NoiseSchedule) -> None:
    i = torch.arange(schedule.num_levels)
    level = schedule.level(schedule.sigma(i, dtype=F64))
    assert_close(level, i.to(F64), rtol=0, atol=1e-9)
    mid = (schedule.sigmas[:-1] * schedule.sigmas[1:]).sqrt()
    lv = schedule.level(mid)
    assert bool(((lv > i[:-1]) & (lv < i[1:])).all()), "level() is monotone between table entries"


def _schedule_training_levels(schedule: NoiseSchedule) -> None:
    lv = schedule.sample_levels((20000,), generator=_gen(14))
    assert int(lv.min()) == 0 and int(lv.max()) == schedule.num_levels - 1


SCHEDULE_CHECKS: dict[str, Callable[[NoiseSchedule], None]] = {
    "levels": _schedule_levels,
    "timesteps": _schedule_timesteps,
    "level_inverts_sigma": _schedule_level_inverts_sigma,
    "training_levels": _schedule_training_levels,
}


def schedule_contract(schedule: NoiseSchedule, checks: list[str] | None = None) -> None:
    for name in list(SCHEDULE_CHECKS) if checks is None else checks:
        SCHEDULE_CHECKS[name](schedule)


# ---------------------------------------------------------------------- samplers
def _objective(make: Callable[[Diffusion], Sampler]) -> str:
    """The objective whose network a sampler reads (``Sampler.objective``; a partial's class's)."""
    return getattr(getattr(make, "func", make), "objective", "dsm")


def _diffusion(make: Callable[[Diffusion], Sampler], g: LieGroup, prior: str) -> Diffusion:
    """The test process for ``make``'s sampler: the score's (DSM) or the flow's (Haar prior)."""
    return Diffusion(ConcentratedGaussian(g), LinearSchedule(), prior=prior, objective=_objective(make))


def _oracle(d: Diffusion, centers: torch.Tensor, weights: torch.Tensor | None = None) -> Any:
    """The exact network of a point-mass mixture for ``d``'s objective: the score or the velocity."""
    return FlowOracle(d, centers, weights) if d.objective == "flow" else MixtureOracle(d, centers, weights)


def _tet_modes() -> torch.Tensor:
    from ..symmetry import symmetry_group

    return symmetry_group("tet", dtype=F64)


def _sampler_point_mass(make: Callable[[Diffusion], Sampler], device: torch.device) -> None:
    """With the exact denoiser of a point mass every sample ends at the point (SO3 and SE3)."""
    for gname in ("so3", "se3"):
        g = get_group(gname)
        d = _diffusion(make, g, "haar")
        center = g.sample_uniform((1,), generator=_gen(15), dtype=F64, bound=0.5).to(device)
        sampler = make(d)
        x = sampler.sample(_oracle(d, center), None, 200, 100, _gen(16), dtype=F64, device=device)
        assert x.shape == (1, 200, g.matrix_dim, g.matrix_dim)
        g.check(x)
        err = g.rminus(center.expand_as(x), x)
        ang = err[..., g.rotation_slice].norm(dim=-1).max()
        assert float(ang) < math.radians(0.5), (
            f"{gname}: worst sample {math.degrees(float(ang)):.3f}° off the point"
        )
        if g.matrix_dim == 4:
            terr = (x[..., :3, 3] - center[..., :3, 3]).norm(dim=-1).max()
            assert float(terr) < 1e-3, f"{gname}: translation off by {float(terr):.2e}"


def _sampler_symmetric_mixture(make: Callable[[Diffusion], Sampler], device: torch.device) -> None:
    """12 tetrahedral-symmetric point masses: every sample on a mode, every mode populated."""
    g = SO3()
    d = _diffusion(make, g, "haar")
    r0 = g.sample_uniform((1,), generator=_gen(17), dtype=F64)
    modes = (r0 @ _tet_modes()).to(device)
    x = make(d).sample(_oracle(d, modes), None, 600, 50, _gen(18), dtype=F64, device=device)[0]
    rel = modes.transpose(-1, -2).unsqueeze(0) @ x.unsqueeze(1)  # (N, 12, 3, 3)
    ang = g.log(rel).norm(dim=-1)
    best, idx = ang.min(dim=1)
    assert float(best.max()) < math.radians(0.5), (
        f"worst sample {math.degrees(float(best.max())):.3f}° off a mode"
    )
    frac = torch.bincount(idx, minlength=12).to(F64) / x.shape[0]
    assert float(frac.min()) > 0.03, f"a mode got only {float(frac.min()):.3f} of the samples"


def _sampler_trajectory_and_determinism(make: Callable[[Diffusion], Sampler], device: torch.device) -> None:
    g = get_group("se3")
    d = _diffusion(make, g, "kernel")
    center = g.identity((1, 1), dtype=F64, device=device)
    oracle = _oracle(d, center[0])
    sampler = make(d)
    a, path = sampler.sample(oracle, None, 8, 5, _gen(19), trajectory=True, dtype=F64, device=device)
    assert path.shape == (6, 1, 8, 4, 4), f"trajectory shape {tuple(path.shape)}"
    assert torch.equal(path[-1], a)
    b = sampler.sample(oracle, None, 8, 5, _gen(19), dtype=F64, device=device)
    assert torch.equal(a, b), "same generator seed → same samples"
    calls = []

    def counting(x: torch.Tensor, sigma: torch.Tensor, cond: Any) -> torch.Tensor:
        calls.append(1)
        return oracle(x, sigma, cond)

    sampler.sample(counting, None, 4, 5, _gen(20), dtype=F64, device=device)
    assert len(calls) == sampler.network_calls(5), (
        f"{len(calls)} calls vs network_calls {sampler.network_calls(5)}"
    )


def _weighted_modes() -> tuple[torch.Tensor, torch.Tensor]:
    """Four rotations of the tetrahedral group (120° apart) with weights 0.4 / 0.3 / 0.2 / 0.1."""
    return _tet_modes()[:4], torch.tensor([0.4, 0.3, 0.2, 0.1], dtype=F64)


def _mode_shares(g: LieGroup, modes: torch.Tensor, x: torch.Tensor) -> tuple[float, torch.Tensor]:
    """(worst angle to the nearest mode, share of the samples at each mode)."""
    rel = modes.transpose(-1, -2).unsqueeze(0) @ x.unsqueeze(1)
    best, idx = g.log(rel).norm(dim=-1).min(dim=1)
    return float(best.max()), torch.bincount(idx, minlength=modes.shape[0]).to(F64) / x.shape[0]


@functools.lru_cache(maxsize=8)
def _reference_shares(device: str, objective: str = "dsm") -> torch.Tensor:
    """The shares the exact ODE of the objective gives from the Haar prior with 100 Heun steps (199
    NFE): the score's probability-flow ODE — not exactly the weights: at σ_max = 1 the noisy law is not
    yet Haar-uniform, which pulls every sampler's shares toward uniform alike (the random walk at 100
    steps: 0.35/0.29/0.23/0.13) — or the flow's own ODE, which starts from the Haar prior exactly
    (0.42/0.29/0.19/0.10)."""
    from ..diffusion.flow import FlowHeunSampler
    from ..diffusion.ode import HeunSampler

    g = SO3()
    d = Diffusion(ConcentratedGaussian(g), LinearSchedule(), prior="haar", objective=objective)
    modes, w = _weighted_modes()
    modes = modes.to(device)
    heun = FlowHeunSampler if objective == "flow" else HeunSampler
    x = heun(d).sample(_oracle(d, modes, w.to(device)), None, 4000, 100, _gen(21), dtype=F64, device=device)
    return _mode_shares(g, modes, x[0])[1].cpu()


def _sampler_five_nfe(make: Callable[[Diffusion], Sampler], device: torch.device) -> None:
    """Samplers that claim few steps (``few_nfe``): with the exact score (or velocity) and 5 network evaluations
    every sample lands on a mode (a point mass on SO3 and SE3; a weighted 4-mode mixture) and the
    modes keep their weights (shares in the weights' order, each within 0.07 of the exact flow's —
    uniform shares would be 0.095 off)."""
    probe = make(_diffusion(make, SO3(), "haar"))
    if not type(probe).few_nfe:
        return  # a many-step sampler (the random walk): not held to 5 evaluations
    for gname in ("so3", "se3"):
        g = get_group(gname)
        d = _diffusion(make, g, "haar")
        sampler = make(d)
        steps = sampler.steps_for_nfe(5)
        assert sampler.network_calls(steps) <= 5
        center = g.sample_uniform((1,), generator=_gen(22), dtype=F64, bound=0.5).to(device)
        x = sampler.sample(_oracle(d, center), None, 200, steps, _gen(23), dtype=F64, device=device)
        err = g.rminus(center.expand_as(x), x)
        ang = float(err[..., g.rotation_slice].norm(dim=-1).max())
        assert ang < math.radians(0.5), f"{gname}: 5 NFE, worst sample {math.degrees(ang):.3f}° off the point"
        if g.matrix_dim == 4:
            terr = float((x[..., :3, 3] - center[..., :3, 3]).norm(dim=-1).max())
            assert terr < 1e-3, f"{gname}: 5 NFE, translation off by {terr:.2e}"
    g = SO3()
    d = _diffusion(make, g, "haar")
    sampler = make(d)
    modes, w = _weighted_modes()
    modes = modes.to(device)
    oracle = _oracle(d, modes, w.to(device))
    x = sampler.sample(oracle, None, 2000, sampler.steps_for_nfe(5), _gen(24), dtype=F64, device=device)[0]
    worst, shares = _mode_shares(g, modes, x)
    shares = shares.cpu()
    assert worst < math.radians(0.5), (
        f"weighted mixture, 5 NFE: worst sample {math.degrees(worst):.3f}° off a mode"
    )
    ref = _reference_shares(str(device), _objective(make))
    assert bool((shares[:-1] > shares[1:]).all()), f"5 NFE shares {shares.tolist()} not in the weights' order"
    gap = float((shares - ref).abs().max())
    assert gap < 0.07, (
        f"5 NFE shares {[round(v, 3) for v in shares.tolist()]} vs the exact flow's {[round(v, 3) for v in ref.tolist()]}"
    )


SAMPLER_CHECKS: dict[str, Callable[[Callable[[Diffusion], Sampler], torch.device], None]] = {
    "point_mass": _sampler_point_mass,
    "symmetric_mixture": _sampler_symmetric_mixture,
    "trajectory_and_determinism": _sampler_trajectory_and_determinism,
    "five_nfe": _sampler_five_nfe,
}


def sampler_contract(
    make: Callable[[Diffusion], Sampler], device: torch.device | str = "cpu", checks: list[str] | None = None
) -> None:
    """``make(diffusion) → Sampler`` (a class or a ``functools.partial`` with options)."""
    _run(SAMPLER_CHECKS, make, torch.device(device), checks)


def _run(
    table: dict[str, Callable[..., None]], obj: Any, device: torch.device, checks: list[str] | None
) -> None:
    names = list(table) if checks is None else checks
    unknown = [n for n in names if n not in table]
    if unknown:
        raise KeyError(f"unknown checks {unknown}; available: {', '.join(table)}")
    for name in names:
        try:
            table[name](obj, device)
        except AssertionError as e:
            raise AssertionError(f"{name}: {e}") from e
