"""``ConcentratedGaussian`` (paper Eq. 3): density, invariance, score, pushforward density, sampling."""

import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import ConcentratedGaussian
from posediff.lie import SO3, get_group, registered_groups

F64 = torch.float64
GROUPS = ["so3", "r3so3", "se3", "se2"]


def random_tangent(group_name: str, n: int, seed: int, max_angle: float = 3.0) -> torch.Tensor:
    g = get_group(group_name)
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(n, g.dim, generator=gen, dtype=F64)
    rot = z[:, g.rotation_slice]
    angle = max_angle * torch.rand(n, 1, generator=gen, dtype=F64)
    z[:, g.rotation_slice] = rot / rot.norm(dim=-1, keepdim=True) * angle
    return z


# ----------------------------------------------------------------------------- log_prob
def test_log_prob_hand_computed_so3() -> None:
    k = ConcentratedGaussian("so3")
    z = torch.tensor([0.3, -0.4, 1.2], dtype=F64)  # |z|² = 1.69
    y = SO3().exp(z)
    sigma = 0.5
    expected = -0.5 * 1.69 / 0.25 - 3 * math.log(0.5) - 1.5 * math.log(2 * math.pi)
    assert float(k.log_prob(y, SO3().identity(dtype=F64), sigma)) == pytest.approx(expected, rel=1e-12)
    assert float(k.log_prob_tangent(z, sigma)) == pytest.approx(expected, rel=1e-12)


def test_log_prob_hand_computed_se3_with_scales() -> None:
    g = get_group("se3")
    k = ConcentratedGaussian(g, translation_scale=2.0, rotation_scale=0.5)
    z = torch.tensor([1.0, -2.0, 0.5, 0.1, 0.2, -0.3], dtype=F64)
    x = g.sample_uniform((), generator=torch.Generator().manual_seed(0), dtype=F64)
    sigma = 0.4  # σ_c = 0.8 on ρ, 0.2 on φ
    quad = (1 + 4 + 0.25) / 0.64 + (0.01 + 0.04 + 0.09) / 0.04
    expected = -0.5 * quad - 3 * math.log(0.8) - 3 * math.log(0.2) - 3 * math.log(2 * math.pi)
    assert float(k.log_prob(g.rplus(x, z), x, sigma)) == pytest.approx(expected, rel=1e-10)


def test_log_prob_per_sample_sigma() -> None:
    k = ConcentratedGaussian("r3so3")
    z = random_tangent("r3so3", 5, seed=1)
    sigma = torch.tensor([0.1, 0.2, 0.5, 1.0, 3.0], dtype=F64)
    expected = -0.5 * z.square().sum(-1) / sigma**2 - 6 * sigma.log() - 3 * math.log(2 * math.pi)
    assert_close(k.log_prob_tangent(z, sigma), expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize("group_name", GROUPS)
def test_log_prob_is_left_invariant(group_name: str) -> None:
    g = get_group(group_name)
    k = ConcentratedGaussian(g, translation_scale=1.5, rotation_scale=0.7)
    gen = torch.Generator().manual_seed(2)
    x = g.sample_uniform((32,), generator=gen, dtype=F64, bound=3.0)
    y = g.rplus(x, random_tangent(group_name, 32, seed=3))
    h = g.sample_uniform((32,), generator=gen, dtype=F64, bound=3.0)
    lp = k.log_prob(y, x, 0.6)
    assert_close(k.log_prob(g.compose(h, y), g.compose(h, x), 0.6), lp, rtol=1e-9, atol=1e-9)
    # but not right-invariant on SE3/SE2 (the test can fail); on SO3 the isotropic density is
    # conjugation-invariant and on R3SO3 a direct product of such, so both are bi-invariant
    if group_name in ("se3", "se2"):
        assert not torch.allclose(k.log_prob(g.compose(y, h), g.compose(x, h), 0.6), lp, rtol=1e-3)


# ----------------------------------------------------------------------------- score
def _autograd_score(k: ConcentratedGaussian, y: torch.Tensor, x: torch.Tensor, sigma: float) -> torch.Tensor:
    """∂/∂τ log p(Y·Exp(τ) | X) at τ = 0 (paper Eq. 4 / 18), written out here."""
    tau = torch.zeros(*y.shape[:-2], k.dim, dtype=y.dtype, requires_grad=True)
    lp = k.log_prob(k.group.rplus(y, tau), x, sigma)
    (grad,) = torch.autograd.grad(lp.sum(), tau)
    return grad


@pytest.mark.parametrize("group_name", GROUPS)
@pytest.mark.parametrize("scales", [(1.0, 1.0), (2.0, 0.5)])
def test_score_tangent_is_autograd_of_log_prob(group_name: str, scales: tuple[float, float]) -> None:
    g = get_group(group_name)
    k = ConcentratedGaussian(g, translation_scale=scales[0], rotation_scale=scales[1])
    x = g.sample_uniform((48,), generator=torch.Generator().manual_seed(4), dtype=F64)
    z = random_tangent(group_name, 48, seed=5)
    y = g.rplus(x, z)
    for sigma in (0.05, 0.8):
        expected = _autograd_score(k, y, x, sigma)
        scale = expected.abs().amax(-1, keepdim=True)
        assert_close(k.score_tangent(z, sigma) / scale, expected / scale, rtol=0, atol=1e-10)
        assert_close(k.score(y, x, sigma) / scale, expected / scale, rtol=0, atol=1e-9)


@pytest.mark.parametrize("group_name", GROUPS)
def test_grad_log_prob_tangent_matches_autograd(group_name: str) -> None:
    k = ConcentratedGaussian(group_name, translation_scale=3.0, rotation_scale=0.25)
    z = random_tangent(group_name, 16, seed=6).requires_grad_(True)
    (grad,) = torch.autograd.grad(k.log_prob_tangent(z, 0.3).sum(), z)
    assert_close(k.grad_log_prob_tangent(z.detach(), 0.3), grad, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------- pushforward density on SO3
def _ball_integral(k: ConcentratedGaussian, sigma: float, *, pushforward: bool) -> float:
    """∫_SO3 p dHaar over the ball |z| ≤ π, dHaar = 2(1 − cos θ)/θ² dz (isotropic p: a 1-D integral in θ)."""
    nodes, weights = np.polynomial.legendre.leggauss(200)
    theta = torch.tensor((nodes + 1) / 2 * math.pi, dtype=F64)
    w = torch.tensor(weights * math.pi / 2, dtype=F64)
    axis = torch.tensor([0.48, 0.6, 0.64], dtype=F64)  # unit; the density is isotropic
    y = SO3().exp(theta[:, None] * axis)
    x = SO3().identity((200,), dtype=F64)
    lp = k.pushforward_log_prob(y, x, sigma) if pushforward else k.log_prob(y, x, sigma)
    # 4πθ² (shell area) × 2(1 − cos θ)/θ² (Haar volume element) = 8π(1 − cos θ)
    return float((lp.exp() * 8 * math.pi * (1 - theta.cos()) * w).sum())


@pytest.mark.parametrize("sigma", [0.5, 1.0, 0.1])
def test_pushforward_integrates_to_one_on_so3(sigma: float) -> None:
    k = ConcentratedGaussian("so3")
    assert _ball_integral(k, sigma, pushforward=True) == pytest.approx(1.0, abs=1e-3)


def test_log_prob_is_normalised_only_as_sigma_goes_to_zero() -> None:
    """The reference measure of ``log_prob`` is Haar; Eq. 3 is a density of it only approximately."""
    k = ConcentratedGaussian("so3")
    mass = {s: _ball_integral(k, s, pushforward=False) for s in (0.05, 0.5, 1.0)}
    assert mass[0.05] == pytest.approx(1.0, abs=2e-3)
    assert mass[0.5] < 0.97 and mass[1.0] < 0.85
    assert mass[0.05] > mass[0.5] > mass[1.0]


def test_pushforward_is_log_prob_minus_log_det_for_small_sigma() -> None:
    g = SO3()
    k = ConcentratedGaussian(g)
    x = g.sample_uniform((32,), generator=torch.Generator().manual_seed(7), dtype=F64)
    z = random_tangent("so3", 32, seed=8, max_angle=0.3)
    y = g.rplus(x, z)
    theta = z.norm(dim=-1)
    log_det = 2 * torch.log(torch.sin(theta / 2) / (theta / 2))  # det J_r = 2(1 − cos θ)/θ² on SO3
    expected = k.log_prob(y, x, 0.05) - log_det
    assert_close(k.pushforward_log_prob(y, x, 0.05), expected, rtol=1e-10, atol=1e-10)
    assert_close(log_det, torch.linalg.det(g.jac_right(z)).log(), rtol=1e-10, atol=1e-12)
    # at large σ the wrapped preimages add mass: the pushforward exceeds the single-chart term near π
    far = 3.0 * torch.nn.functional.normalize(random_tangent("so3", 8, seed=9), dim=-1)
    yf = g.exp(far)
    single = k.log_prob(yf, g.identity((8,), dtype=F64), 1.0) - torch.linalg.det(g.jac_right(far)).log()
    assert bool((k.pushforward_log_prob(yf, g.identity((8,), dtype=F64), 1.0) > single + 0.1).all())


def _pushforward_oracle(
    k: ConcentratedGaussian, y: torch.Tensor, sigma: float, wraps: int = 2
) -> torch.Tensor:
    """Σ_n N(z_n; 0, σ²I)/|det J_r(z_n)| over the preimages ``z_n`` of ``Y`` (mean = identity), built from
    ``exp`` alone: ``φ_n = φ₀ + 2πn·axis`` and, since the translation of ``Exp(ρ, φ)`` is linear in ρ,
    ``ρ_n = V(φ_n)⁻¹ t`` with the columns of ``V(φ)`` read off ``Exp(e_i, φ)``."""
    g = k.group
    z0 = g.log(y)
    sl = g.rotation_slice
    trans = [i for i in range(g.dim) if not sl.start <= i < sl.stop]
    d = g.matrix_dim - 1
    phi = z0[..., sl]
    axis = phi / phi.norm(dim=-1, keepdim=True)
    t = y[..., :d, d]
    terms = []
    for n in range(-wraps, wraps + 1):
        zn = z0.clone()
        zn[..., sl] = phi + 2 * math.pi * n * axis
        if trans:
            cols = []
            for i in trans:
                e = zn.clone()
                e[..., trans] = 0.0
                e[..., i] = 1.0
                cols.append(g.exp(e)[..., :d, d])
            v = torch.stack(cols, -1)
            zn[..., trans] = torch.linalg.solve(v, t.unsqueeze(-1)).squeeze(-1)
        log_n = (
            -0.5 * (zn / sigma).square().sum(-1)
            - g.dim * math.log(sigma)
            - 0.5 * g.dim * math.log(2 * math.pi)
        )
        terms.append(log_n - torch.linalg.det(g.jac_right(zn)).abs().log())
    return torch.logsumexp(torch.stack(terms), 0)


@pytest.mark.parametrize(
    "group_name",
    [
        "so3",
        "r3so3",
        "se3",
        "se2",
    ],
)
def test_pushforward_matches_preimage_enumeration(group_name: str) -> None:
    """Near θ = π at σ = 1 the wrapped preimage (n = −1) carries about as much mass as the principal one."""
    g = get_group(group_name)
    k = ConcentratedGaussian(g)
    z = random_tangent(group_name, 16, seed=15)
    sl = g.rotation_slice
    z[:, sl] = (
        z[:, sl] / z[:, sl].norm(dim=-1, keepdim=True) * torch.linspace(2.6, 3.1, 16, dtype=F64)[:, None]
    )
    y = g.exp(z)
    expected = _pushforward_oracle(k, y, 1.0)
    assert_close(k.pushforward_log_prob(y, g.identity((16,), dtype=F64), 1.0), expected, rtol=0, atol=1e-9)
    # the wrapped terms matter here: the single principal-chart term is far off
    single = k.log_prob(y, g.identity((16,), dtype=F64), 1.0) - torch.linalg.det(g.jac_right(z)).abs().log()
    # (SE2's single planar angle puts a little less mass on the wrapped preimage: 0.046 measured)
    assert float((expected - single).min()) > (0.03 if group_name == "se2" else 0.05)


# ----------------------------------------------------------------------------- sampling
@pytest.mark.parametrize("group_name", ["so3", "se3", "se2"])
def test_sample_covariance(group_name: str) -> None:
    g = get_group(group_name)
    k = ConcentratedGaussian(g, translation_scale=2.0, rotation_scale=0.5)
    x = g.sample_uniform((), generator=torch.Generator().manual_seed(10), dtype=F64)
    y, z = k.sample(x.expand(40000, -1, -1), 0.05, generator=torch.Generator().manual_seed(11))
    assert y.shape == (40000, g.matrix_dim, g.matrix_dim) and z.shape == (40000, g.dim)
    assert_close(y, g.rplus(x, z), rtol=0, atol=1e-12)
    sig_c = k.component_sigma(0.05, z[0])
    cov = z.T @ z / z.shape[0]
    assert_close(cov.diagonal(), sig_c**2, rtol=0.1, atol=0)
    off = cov - torch.diag(cov.diagonal())
    assert float((off.abs() / torch.outer(sig_c, sig_c)).max()) < 0.1
    assert float(z.mean(0).div(sig_c).abs().max()) < 0.05


def test_sample_tangent_shapes_and_wrap() -> None:
    k = ConcentratedGaussian("so3")
    sigma = torch.tensor([0.1, 5.0], dtype=F64)
    z = k.sample_tangent(sigma, batch_shape=(1000, 2), generator=torch.Generator().manual_seed(12))
    assert z.shape == (1000, 2, 3) and z.dtype == F64
    assert float(z.norm(dim=-1).max()) <= math.pi + 1e-12  # wrapped to the principal chart
    raw = ConcentratedGaussian("so3", wrap=False).sample_tangent(
        sigma, batch_shape=(1000, 2), generator=torch.Generator().manual_seed(12)
    )
    assert float(raw.norm(dim=-1).max()) > math.pi
    assert_close(SO3().exp(raw), SO3().exp(z), rtol=0, atol=1e-10)
    assert k.sample_tangent(0.3).shape == (3,)


def test_generator_determinism() -> None:
    k = ConcentratedGaussian("se3")
    x = get_group("se3").identity((64,), dtype=F64)
    a = k.sample(x, 0.3, generator=torch.Generator().manual_seed(13))
    b = k.sample(x, 0.3, generator=torch.Generator().manual_seed(13))
    c = k.sample(x, 0.3, generator=torch.Generator().manual_seed(14))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[1], c[1])


# ----------------------------------------------------------------------------- construction
def test_bad_group_name_lists_registered_groups() -> None:
    known = ", ".join(sorted(registered_groups()))
    assert "se3" in known and "so3" in known
    with pytest.raises(KeyError, match=known):
        ConcentratedGaussian("sim3x")


@pytest.mark.parametrize(
    "kw", [{"translation_scale": 0.0}, {"rotation_scale": 0.0}, {"rotation_scale": -1.0}]
)
def test_non_positive_scales(kw: dict) -> None:
    with pytest.raises(ValueError, match="positive"):
        ConcentratedGaussian("se3", **kw)


def test_not_a_group() -> None:
    with pytest.raises(TypeError):
        ConcentratedGaussian(3)  # type: ignore[arg-type]


def test_scales_and_component_sigma() -> None:
    k = ConcentratedGaussian("se3", translation_scale=2.0, rotation_scale=0.5)
    assert_close(k.scales(dtype=F64), torch.tensor([2.0] * 3 + [0.5] * 3, dtype=F64))
    z = torch.zeros(4, 6, dtype=F64)
    sig = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=F64)
    assert_close(k.component_sigma(sig, z), sig[:, None] * torch.tensor([2.0] * 3 + [0.5] * 3, dtype=F64))
    k2 = ConcentratedGaussian("so3", translation_scale=2.0, rotation_scale=0.5)
    assert_close(k2.scales(dtype=F64), torch.full((3,), 0.5, dtype=F64))
