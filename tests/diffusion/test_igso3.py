"""The isotropic Gaussian on SO(3) (paper supp. Eq. 14–15): density, score, sampling, kernel."""

import math

import mpmath  # installed with torch (torch → sympy → mpmath); used as an exact oracle
import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.diffusion import igso3 as ig
from posediff.diffusion.igso3 import (
    IGSO3,
    eps_from_sigma,
    igso3_angle_quantile,
    igso3_dlog_density,
    igso3_log_density,
    igso3_quantile_table,
    igso3_series_lmax,
    sample_igso3,
    sample_igso3_angle,
)
from posediff.lie import get_group

F64 = torch.float64
F32 = torch.float32


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _angle_grid(n: int = 20_001) -> tuple[Tensor, Tensor, Tensor]:
    """(t, ω, dω/dt) for ω = π t³: dense near 0, where the mass of small-ε laws sits; integrals
    are taken in t, where the integrand is smooth."""
    t = torch.linspace(0.0, 1.0, n, dtype=F64)
    return t, math.pi * t**3, 3.0 * math.pi * t**2


def _reference_cdf(sigma: float, n: int = 30_001) -> tuple[Tensor, Tensor]:
    """(ω grid, CDF) of the angle by cumulative trapezoid on a fine grid (independent of the table)."""
    t, w, dw = _angle_grid(n)
    dens = (1.0 - torch.cos(w)) / math.pi * igso3_log_density(w, eps_from_sigma(sigma)).exp() * dw
    cdf = torch.cumulative_trapezoid(dens, t)
    cdf = torch.cat([cdf.new_zeros(1), cdf])
    return w, cdf / cdf[-1]


def _interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    j = torch.searchsorted(xp, x).clamp(1, xp.numel() - 1)
    x0, x1, f0, f1 = xp[j - 1], xp[j], fp[j - 1], fp[j]
    t = ((x - x0) / (x1 - x0).clamp_min(1e-300)).clamp(0.0, 1.0)
    return f0 + t * (f1 - f0)


def _ks(samples: Tensor, cdf_at: Tensor) -> float:
    """Kolmogorov–Smirnov distance given the reference CDF at the sorted samples."""
    n = samples.numel()
    i = torch.arange(1, n + 1, dtype=F64)
    return float(torch.maximum(i / n - cdf_at, cdf_at - (i - 1) / n).max())


def _chi3_cdf(r: Tensor) -> Tensor:
    return torch.erf(r / math.sqrt(2.0)) - math.sqrt(2.0 / math.pi) * r * torch.exp(-0.5 * r * r)


def _mp_log_f(omega: float, eps: float) -> float:
    """log f_ε(ω) in 50-digit arithmetic: Eq. 14 for ε ≥ 0.5, its full Poisson sum (all wraps,
    of which Eq. 15 keeps k ∈ {−1, 0, 1}) below."""
    mpmath.mp.dps = 50
    om = mpmath.mpf(omega) if omega > 0 else mpmath.mpf("1e-40")
    e = mpmath.mpf(eps)
    if eps < 0.5:
        s = mpmath.fsum(
            (-1) ** k * (om + 2 * mpmath.pi * k) * mpmath.exp(-((om + 2 * mpmath.pi * k) ** 2) / (4 * e))
            for k in range(-8, 9)
        )
        val = mpmath.sqrt(mpmath.pi) * e**-1.5 * mpmath.exp(e / 4) / (2 * mpmath.sin(om / 2)) * s
    else:
        val = mpmath.fsum(
            (2 * l + 1)
            * mpmath.exp(-l * (l + 1) * e)
            * mpmath.sin((l + mpmath.mpf(1) / 2) * om)
            / mpmath.sin(om / 2)
            for l in range(80)
        )
    return float(mpmath.log(val))


# ------------------------------------------------------------------------------------- density
@pytest.mark.parametrize("eps", [1e-3, 0.01, 0.1, 0.5, 1.0, 2.0, 5.0])
def test_density_integrates_to_one(eps: float) -> None:
    """∫₀^π (1 − cos ω)/π f_ε(ω) dω = 1 (measured |error| ≤ 2.5e-9, the trapezoid rule's)."""
    methods = ["auto", "series"] + (["closed_form"] if eps <= 1.0 else [])
    for method in methods:
        # the series at small ε has hundreds of terms: a coarser grid suffices (error 1.4e-13)
        t, w, dw = _angle_grid(4001 if method == "series" and eps < 0.05 else 20_001)
        f = igso3_log_density(w, eps, method=method).exp()
        mass = torch.trapezoid((1.0 - torch.cos(w)) / math.pi * f * dw, t)
        assert_close(mass, torch.tensor(1.0, dtype=F64), atol=1e-8, rtol=0, msg=f"{method} at ε={eps}")


@pytest.mark.parametrize("eps", [1e-6, 1e-3, 0.05, 0.3, 0.9, 1.0, 3.0])
def test_log_density_matches_high_precision_oracle(eps: float) -> None:
    omegas = [0.0, 1e-8, 1e-3, 0.1, 1.0, 2.0, math.pi - 1e-6, math.pi]
    ref = torch.tensor([_mp_log_f(o, eps) for o in omegas], dtype=F64)
    got = igso3_log_density(torch.tensor(omegas, dtype=F64), eps)
    # log-space error ≈ relative error of f; Eq. 15 is 4e-9 from exact at ε → 1⁻ (its dropped wraps)
    tol = 1e-8 if 0.5 < eps < 1.0 else 1e-12
    assert_close(got, ref, rtol=tol, atol=tol)
    if eps >= 0.05:  # the series wherever it does not cancel: here all the ω above for ε ≥ 0.3
        ser = igso3_log_density(torch.tensor(omegas, dtype=F64), eps, method="series")
        keep = ref > ref.max() - math.log(1e6)
        assert_close(ser[keep], ref[keep], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("eps", [1e-3, 0.01, 0.1, 0.25, 0.5])
def test_series_matches_closed_form(eps: float) -> None:
    """Measured max relative difference where f ≥ 1e-8 f(0): ≤ 1.1e-8 (ε = 0.1, the series' round-off
    cancellation); over all of [0, π] for ε ∈ {0.25, 0.5}: 4e-13 and 5e-15."""
    w = torch.linspace(0.0, math.pi, 20_001, dtype=F64)
    series = igso3_log_density(w, eps, method="series")
    closed = igso3_log_density(w, eps, method="closed_form")
    keep = series > series.max() - math.log(1e8)
    rel = (series - closed).exp().sub(1.0).abs()
    assert float(rel[keep].max()) < 3e-8
    if eps >= 0.25:
        assert float(rel.max()) < 1e-12


def test_auto_is_continuous_at_the_switch() -> None:
    w = torch.linspace(0.0, math.pi, 2001, dtype=F64)
    below = igso3_log_density(w, ig.EPS_SWITCH * (1 - 1e-12))  # Eq. 15
    at = igso3_log_density(w, ig.EPS_SWITCH)  # series
    assert float((below - at).abs().max()) < 1e-8  # measured 4.0e-9
    assert_close(igso3_log_density(w, 0.3), igso3_log_density(w, 0.3, method="closed_form"), rtol=0, atol=0)
    assert_close(igso3_log_density(w, 3.0), igso3_log_density(w, 3.0, method="series"), rtol=0, atol=0)


def test_default_lmax_tail_is_negligible() -> None:
    w = torch.linspace(0.0, math.pi, 1001, dtype=F64)
    for eps in [1e-3, 0.05, 1.0, 4.0]:
        lmax = igso3_series_lmax(eps)
        assert lmax * (lmax + 1) * eps >= ig.SERIES_DECAY
        a = igso3_log_density(w, eps, method="series").exp()
        b = igso3_log_density(w, eps, method="series", lmax=2 * lmax + 10).exp()
        assert float((a - b).abs().max() / b[0]) < 1e-12


def test_density_is_even_periodic_and_broadcasts() -> None:
    w = torch.tensor([0.3, 1.7, 3.0], dtype=F64)
    eps = torch.tensor([[0.05], [2.0]], dtype=F64)
    lp = igso3_log_density(w, eps)
    assert lp.shape == (2, 3)
    assert_close(igso3_log_density(-w, eps), lp)
    assert_close(igso3_log_density(2 * math.pi - w, eps), lp)
    assert_close(igso3_log_density(w + 2 * math.pi, eps), lp)
    with pytest.raises(ValueError, match="auto, series, closed_form"):
        igso3_log_density(w, 0.1, method="nope")


def test_eps_from_sigma() -> None:
    assert eps_from_sigma(0.2) == pytest.approx(0.02)
    assert_close(eps_from_sigma(torch.tensor([1.0, 2.0])), torch.tensor([0.5, 2.0]))


def test_small_sigma_limit_is_the_gaussian() -> None:
    """σ = 0.01: the IG density of a rotation vector, converted from Haar (mass 1) to Lebesgue in
    the tangent (× 2(1 − cos θ)/θ² / 8π²), is the N(0, σ² I₃) density (relative 1e-3)."""
    sigma = 0.01
    z = sigma * torch.randn(2000, 3, generator=_gen(0), dtype=F64)
    z = torch.cat([z, torch.zeros(1, 3, dtype=F64)])
    theta = z.norm(dim=-1)
    log_jac = torch.where(
        theta > 0,
        torch.log(4.0 * torch.sin(theta / 2) ** 2 / theta.clamp_min(1e-300) ** 2),
        torch.zeros_like(theta),
    )
    lebesgue = igso3_log_density(theta, eps_from_sigma(sigma)) + log_jac - math.log(8 * math.pi**2)
    gauss = -0.5 * (theta / sigma) ** 2 - 3 * math.log(sigma) - 1.5 * math.log(2 * math.pi)
    assert float((lebesgue - gauss).abs().max()) < 1e-3
    # the IGSO3 kernel's log_prob_tangent is the Haar (mass 1) density, i.e. the same log f
    kernel = IGSO3("so3")
    assert_close(kernel.log_prob_tangent(z, sigma), igso3_log_density(theta, eps_from_sigma(sigma)))


@pytest.mark.parametrize("group", ["so3", "r3so3"])
def test_reference_measure_relative_to_concentrated_gaussian(group: str) -> None:
    """Haar(mass 1) = Haar(Lebesgue at identity)/8π²: at σ = 0.01 the IGSO3 density minus log 8π²
    is the exact Haar density of the concentrated Gaussian's law (its pushforward_log_prob)."""
    from posediff.diffusion.kernels import ConcentratedGaussian

    ig3, cg = IGSO3(group), ConcentratedGaussian(group)
    x = ig3.group.sample_uniform((500,), generator=_gen(20), dtype=F64)
    x_noisy, _ = cg.sample(x, 0.01, generator=_gen(21))
    lhs = ig3.log_prob(x_noisy, x, 0.01) - math.log(8 * math.pi**2)
    assert float((lhs - cg.pushforward_log_prob(x_noisy, x, 0.01)).abs().max()) < 1e-3


# ----------------------------------------------------------------------------------------- score
def test_dlog_density_matches_finite_differences() -> None:
    w = torch.tensor([0.05, 0.4, 1.0, 2.0, 3.0], dtype=F64)
    for eps in [0.02, 0.5, 0.99, 1.0, 3.0]:
        h = 1e-6
        fd = (igso3_log_density(w + h, eps) - igso3_log_density(w - h, eps)) / (2 * h)
        assert_close(igso3_dlog_density(w, eps), fd, rtol=1e-6, atol=1e-6)
    zero = igso3_dlog_density(torch.tensor([0.0, math.pi], dtype=F64), torch.tensor([0.01, 0.5], dtype=F64))
    assert_close(zero, torch.zeros(2, dtype=F64), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [F32, F64], ids=["float32", "float64"])
def test_finite_at_the_edges(dtype: torch.dtype) -> None:
    omega = torch.tensor([0.0, 1e-8, 1e-3, math.pi - 1e-6, math.pi], dtype=dtype)
    for sigma in [1e-4, 1e-2, 1.0, 3.0]:
        eps = eps_from_sigma(torch.tensor(sigma, dtype=dtype))
        for method in ["auto", "closed_form"] + (["series"] if sigma >= 1 else []):
            w = omega.clone().requires_grad_(True)
            lp = igso3_log_density(w, eps, method=method)
            (g,) = torch.autograd.grad(lp.sum(), w)
            assert lp.dtype == dtype and bool(torch.isfinite(lp).all()), (sigma, method, lp)
            assert bool(torch.isfinite(g).all()), (sigma, method, g)
        assert bool(torch.isfinite(igso3_dlog_density(omega, eps)).all())
        # the kernel's tangent score and density along the same angles
        phi = omega.unsqueeze(-1) * torch.tensor([0.6, -0.8, 0.0], dtype=dtype)
        kernel = IGSO3("so3")
        assert bool(torch.isfinite(kernel.log_prob_tangent(phi, sigma)).all())
        assert bool(torch.isfinite(kernel.grad_log_prob_tangent(phi, sigma)).all())
        assert bool(torch.isfinite(kernel.score_tangent(phi, sigma)).all())
    # float32 agrees with float64 where the angle is exactly representable
    w64 = torch.tensor([0.0, 1e-3, 0.5, 2.0, 3.0], dtype=F64)
    for sigma in [1e-2, 0.3, 1.0, 3.0]:
        ref = igso3_log_density(w64, eps_from_sigma(sigma))
        got = igso3_log_density(w64.to(dtype), eps_from_sigma(torch.tensor(sigma, dtype=dtype)))
        assert_close(got.double(), ref, rtol=1e-5, atol=1e-5)


def _tangents(group: str, gen: torch.Generator) -> Tensor:
    g = get_group(group)
    z = torch.randn(64, g.dim, generator=gen, dtype=F64)
    sl = g.rotation_slice
    # angles across (0, π], plus exactly 0 and near π
    phi = z[:, sl]
    axis = phi / phi.norm(dim=-1, keepdim=True)
    ang = torch.rand(64, generator=gen, dtype=F64) * math.pi
    ang[0], ang[1] = 0.0, math.pi - 1e-9
    z[:, sl] = ang.unsqueeze(-1) * axis
    return z


@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
def test_grad_log_prob_matches_autograd(group: str) -> None:
    kernel = IGSO3(group, translation_scale=2.0, rotation_scale=0.5)
    z = _tangents(group, _gen(1))
    sigma = torch.rand(64, generator=_gen(2), dtype=F64) * 2.5 + 0.05
    grad = kernel.grad_log_prob_tangent(z, sigma)
    zz = z.clone().requires_grad_(True)
    (auto,) = torch.autograd.grad(kernel.log_prob_tangent(zz, sigma).sum(), zz)
    assert_close(grad, auto, rtol=1e-9, atol=1e-9)
    sl = kernel.group.rotation_slice
    assert_close(grad[0, sl], torch.zeros(3, dtype=F64))  # φ = 0: zero by symmetry
    assert bool(torch.isfinite(grad).all())


def test_score_on_so3_is_radial() -> None:
    """J_r⁻ᵀ(φ)φ = φ, so the Stein score is (d log f/dω)·φ/|φ|."""
    kernel = IGSO3("so3")
    z = _tangents("so3", _gen(3))
    sigma = torch.full((64,), 0.7, dtype=F64)
    omega = z.norm(dim=-1)
    unit = z / omega.clamp_min(1e-300).unsqueeze(-1)
    expected = igso3_dlog_density(omega, eps_from_sigma(0.7)).unsqueeze(-1) * unit
    assert_close(kernel.score_tangent(z, sigma), expected, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------------------- sampling
@pytest.mark.parametrize("sigma", [0.05, 0.3, 1.0, 2.0, 0.1234, 5.0])
def test_sampled_angles_match_the_density(sigma: float) -> None:
    """KS distance (20,000 samples) to the numerically integrated CDF; 0.1234 lies between table
    rows and 5.0 above the table (Haar-uniform angles)."""
    angles = sample_igso3_angle(sigma, batch_shape=(20_000,), generator=_gen(4), dtype=F64)
    w, cdf = _reference_cdf(sigma)
    s = angles.sort().values
    assert float(s[0]) >= 0.0 and float(s[-1]) <= math.pi
    assert _ks(s, _interp(s, w, cdf)) < 0.015


def test_small_sigma_sampling_is_chi3() -> None:
    for sigma in [1e-4, 0.01]:  # below the table (exact limit) and inside it
        s = sample_igso3_angle(sigma, batch_shape=(20_000,), generator=_gen(5), dtype=F64).sort().values
        assert _ks(s, _chi3_cdf(s / sigma)) < 0.015
    assert_close(sample_igso3(0.0, batch_shape=(5,), generator=_gen(0)), torch.zeros(5, 3))


def test_quantile_interpolation_between_rows() -> None:
    """At σ between table rows the interpolated quantile is at the right level of a directly
    integrated CDF: max_u |F(Q̂(u)) − u| (measured ≤ 4e-6 over all σ in the table)."""
    u = torch.linspace(0.0, 1.0, 2001, dtype=F64)
    for sigma in [5e-4, 2e-3, 0.1234, 0.777, 1.3, 3.3, 4.0]:
        w, cdf = _reference_cdf(sigma)
        got = igso3_angle_quantile(torch.tensor(sigma, dtype=F64), u)
        assert bool((got[1:] >= got[:-1]).all())
        assert float((_interp(got, w, cdf) - u).abs().max()) < 2e-5, sigma


def test_sampling_per_sample_sigma_generator_and_axes() -> None:
    sigma = torch.tensor([[1e-5, 0.02], [0.5, 1.5], [3.0, 7.0]], dtype=F32)
    a = sample_igso3(sigma, generator=_gen(6))
    b = sample_igso3(sigma, generator=_gen(6))
    assert a.shape == (3, 2, 3) and a.dtype == F32
    assert torch.equal(a, b)
    assert_close(sample_igso3_angle(sigma, generator=_gen(6)), a.norm(dim=-1))
    # the axis is uniform on S²: its mean is 0 and its second moment I/3
    phi = sample_igso3(0.8, batch_shape=(20_000,), generator=_gen(7), dtype=F64)
    axis = phi / phi.norm(dim=-1, keepdim=True)
    assert float(axis.mean(0).abs().max()) < 0.03
    assert_close(axis.T @ axis / 20_000, torch.eye(3, dtype=F64) / 3, atol=0.01, rtol=0)


def test_table_is_built_once() -> None:
    t1 = igso3_quantile_table()
    sample_igso3(torch.rand(100), generator=_gen(8))
    sample_igso3(torch.rand(100, dtype=F64), generator=_gen(8))
    t2 = igso3_quantile_table()
    assert t1 is t2 and ig.TABLE_BUILDS == 1
    assert igso3_quantile_table(F32) is igso3_quantile_table(F32)
    assert igso3_quantile_table(F32).ratio.dtype == F32
    assert t1.ratio.shape == (ig.TABLE_NUM_SIGMA, ig.TABLE_NUM_U)
    assert float((t1.mass - 1).abs().max()) < 1e-6
    # quantiles increase in u; Q/σ → the chi(3) quantile at the smallest σ
    assert bool((t1.ratio[:, 1:] >= t1.ratio[:, :-1]).all())
    med = t1.ratio[0, (t1.u - 0.5).abs().argmin()]
    assert_close(_chi3_cdf(med), t1.u[(t1.u - 0.5).abs().argmin()], atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------- kernel
@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
def test_kernel_on_each_group(group: str) -> None:
    kernel = IGSO3(group, translation_scale=0.5)
    g = kernel.group
    x = g.sample_uniform((4, 5), generator=_gen(9), dtype=F64)
    sigma = torch.rand(4, 5, generator=_gen(10), dtype=F64) * 3
    x_noisy, z = kernel.sample(x, sigma, generator=_gen(11))
    assert x_noisy.shape == x.shape and z.shape == (4, 5, g.dim)
    g.check(x_noisy)
    assert_close(g.rplus(x, z), x_noisy)
    assert float(z[..., g.rotation_slice].norm(dim=-1).max()) <= math.pi + 1e-12
    lp = kernel.log_prob(x_noisy, x, sigma)
    assert lp.shape == (4, 5) and bool(torch.isfinite(lp).all())
    assert_close(lp, kernel.log_prob_tangent(g.rminus(x, x_noisy), sigma))
    assert kernel.score(x_noisy, x, sigma).shape == (4, 5, g.dim)
    # float32 sampling gives valid elements too
    x32, _ = kernel.sample(x.float(), sigma.float(), generator=_gen(12))
    g.check(x32)
    if group != "so3":  # the translation part is N(0, (σ·translation_scale)²)
        zt = kernel.sample_tangent(torch.full((20_000,), 0.4, dtype=F64), generator=_gen(13))
        assert_close(zt[:, :3].std(0), torch.full((3,), 0.2, dtype=F64), rtol=0.03, atol=0)


def test_kernel_density_is_normalised_wrt_haar() -> None:
    """E_{R ~ Haar(mass 1)}[q(Log R)] = 1 (the reference measure of the rotation factor)."""
    so3 = get_group("so3")
    r = so3.sample_uniform((20_000,), generator=_gen(14), dtype=F64)
    q = IGSO3("so3").log_prob_tangent(so3.log(r), 1.5).exp()
    assert abs(float(q.mean()) - 1.0) < 0.02


def test_unsupported_group() -> None:
    with pytest.raises(ValueError, match="so3, r3so3, se3"):
        IGSO3("se2")
    assert IGSO3.name == "igso3"
