"""``Diffusion``: perturbation, training targets and losses, output parameterisation, priors."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import ConcentratedGaussian, Diffusion, LinearSchedule, PowerSchedule
from posediff.lie import SE3, SO3, get_group

F64 = torch.float64
GROUPS = ["so3", "r3so3", "se3", "se2"]


def make(group_name: str = "se3", *, scales: tuple[float, float] = (1.0, 1.0), **kw) -> Diffusion:
    kernel = ConcentratedGaussian(group_name, translation_scale=scales[0], rotation_scale=scales[1])
    return Diffusion(kernel, kw.pop("schedule", PowerSchedule()), **kw)


def sigma_c(d: Diffusion, sigma: torch.Tensor) -> torch.Tensor:
    """Per-component σ written out by hand (translation_scale on ρ, rotation_scale on φ)."""
    g = d.group
    out = sigma.unsqueeze(-1).expand(*sigma.shape, g.dim).clone() * d.kernel.translation_scale
    out[..., g.rotation_slice] = sigma.unsqueeze(-1) * d.kernel.rotation_scale
    return out


def clean(group_name: str, n: int, seed: int = 0) -> torch.Tensor:
    return get_group(group_name).sample_uniform(
        (n,), generator=torch.Generator().manual_seed(seed), dtype=F64
    )


# ----------------------------------------------------------------------------- perturb
@pytest.mark.parametrize("group_name", GROUPS)
def test_perturb_shapes(group_name: str) -> None:
    d = make(group_name)
    g = d.group
    n = g.matrix_dim
    x0 = clean(group_name, 3)
    b = d.perturb(x0, num_noisy=5, generator=torch.Generator().manual_seed(1))
    assert b.x_noisy.shape == (3, 5, n, n)
    assert b.z.shape == b.target.shape == (3, 5, g.dim)
    assert b.sigma.shape == b.level.shape == (3, 5)
    assert b.level.dtype == torch.long and b.sigma.dtype == F64 and b.x_noisy.dtype == F64
    assert_close(b.sigma, d.schedule.sigma(b.level, dtype=F64))
    b1 = d.perturb(x0, generator=torch.Generator().manual_seed(1))
    assert b1.x_noisy.shape == (3, n, n) and b1.z.shape == (3, g.dim) and b1.sigma.shape == (3,)
    # a given level broadcasts over the batch
    b2 = d.perturb(x0, num_noisy=4, levels=torch.tensor(7), generator=torch.Generator().manual_seed(1))
    assert bool((b2.level == 7).all())
    assert_close(b2.sigma, torch.full((3, 4), float(d.schedule.sigmas[7]), dtype=F64))


@pytest.mark.parametrize("group_name", GROUPS)
@pytest.mark.parametrize("scales", [(1.0, 1.0), (2.0, 0.5)])
def test_surrogate_targets_for_both_outputs(group_name: str, scales: tuple[float, float]) -> None:
    x0 = clean(group_name, 4)
    for output, sign in (("score", -1.0), ("noise", 1.0)):
        d = make(group_name, scales=scales, output=output)
        b = d.perturb(x0, num_noisy=8, generator=torch.Generator().manual_seed(2))
        assert_close(b.target, sign * b.z / sigma_c(d, b.sigma), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("group_name", GROUPS)
@pytest.mark.parametrize("output", ["score", "noise"])
@pytest.mark.parametrize("score", ["surrogate", "closed_form"])
def test_to_score_inverts_from_score(group_name: str, output: str, score: str) -> None:
    d = make(group_name, scales=(2.0, 0.5), output=output, score=score)
    gen = torch.Generator().manual_seed(3)
    s = torch.randn(6, d.group.dim, generator=gen, dtype=F64)
    sigma = torch.linspace(1e-3, 1.0, 6, dtype=F64)
    assert_close(d.to_score(d.from_score(s, sigma), sigma), s, rtol=1e-12, atol=0)
    # and the target of a perturbation maps back to the chosen score
    b = d.perturb(clean(group_name, 6), generator=gen)
    assert_close(d.to_score(b.target, b.sigma), d.score_target(d.kernel, b.z, b.sigma), rtol=1e-12, atol=0)


@pytest.mark.parametrize("group_name", ["so3", "se3"])
def test_perturb_is_rplus_and_z_is_principal(group_name: str) -> None:
    """σ = 2: many raw rotation draws exceed π; the stored z is the principal one of the same element."""
    g = get_group(group_name)
    d = make(group_name, schedule=LinearSchedule(num_levels=2, sigma_min=1.0, sigma_max=2.0))
    x0 = clean(group_name, 400, seed=4)
    b = d.perturb(x0, levels=torch.tensor(1), generator=torch.Generator().manual_seed(5))
    assert_close(b.x_noisy, g.rplus(x0, b.z), rtol=0, atol=1e-12)
    angle = b.z[..., g.rotation_slice].norm(dim=-1)
    assert float(angle.max()) <= math.pi + 1e-12
    assert_close(b.z, g.rminus(x0, b.x_noisy), rtol=0, atol=1e-9)
    # the same draw without wrapping: a good fraction is beyond π, and lands on the same element
    raw = ConcentratedGaussian(group_name, wrap=False).sample_tangent(
        torch.full((400,), 2.0, dtype=F64), generator=torch.Generator().manual_seed(5)
    )
    far = raw[..., g.rotation_slice].norm(dim=-1) > math.pi
    assert int(far.sum()) > 50
    assert not torch.allclose(raw[far], b.z[far])
    assert_close(g.rplus(x0, raw), b.x_noisy, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- loss
@pytest.mark.parametrize("group_name", GROUPS)
@pytest.mark.parametrize("loss", ["tangent_l2", "chordal"])
@pytest.mark.parametrize("output", ["score", "noise"])
def test_loss_zero_at_target_positive_elsewhere(group_name: str, loss: str, output: str) -> None:
    d = make(group_name, loss=loss, output=output)
    b = d.perturb(clean(group_name, 16), generator=torch.Generator().manual_seed(6))
    assert float(d.loss(b.target.clone(), b)) == 0.0
    off = b.target + 0.01 * torch.randn(b.target.shape, generator=torch.Generator().manual_seed(7), dtype=F64)
    assert float(d.loss(off, b)) > 0.0
    # only one component, one sample off: still positive
    one = b.target.clone()
    one[3, 0] += 0.1
    assert float(d.loss(one, b)) > 0.0


def test_tangent_l2_value() -> None:
    d = make("se3")
    b = d.perturb(clean("se3", 4), generator=torch.Generator().manual_seed(8))
    delta = torch.arange(24, dtype=F64).reshape(4, 6) / 10
    assert_close(d.loss(b.target + delta, b), delta.square().sum(-1).mean(), rtol=1e-12, atol=0)


@pytest.mark.parametrize("group_name", ["so3", "se3"])
def test_chordal_loss_value(group_name: str) -> None:
    g = get_group(group_name)
    d = make(group_name, loss="chordal")
    b = d.perturb(clean(group_name, 4), generator=torch.Generator().manual_seed(9))
    out = b.target + 0.3
    expected = (g.exp(out) - g.exp(b.target)).square().sum((-2, -1)).mean()
    assert_close(d.loss(out, b), expected)


def test_chordal_small_rotation_error_is_twice_tangent_l2() -> None:
    d = make("so3", loss="chordal")
    b = d.perturb(clean("so3", 8), generator=torch.Generator().manual_seed(10))
    target = torch.tensor([0.3, -0.2, 0.1], dtype=F64).expand_as(b.target).clone()  # far from the cut locus
    b = dataclasses.replace(b, target=target)
    axis = torch.tensor([0.0, 0.6, 0.8], dtype=F64)
    rot = SO3().exp(target)
    out = SO3().log(rot @ SO3().exp(1e-4 * axis))  # a rotation 1e-4 rad away
    assert_close(d.loss(out, b), torch.tensor(2e-8, dtype=F64), rtol=1e-4, atol=0)


def test_weighting_none_divides_by_sigma_c_squared() -> None:
    x0 = clean("se3", 8)
    kw = dict(scales=(2.0, 0.5), rotation_weight=3.0, translation_weight=0.5)
    d2 = make("se3", weighting="sigma2", **kw)
    d0 = make("se3", weighting="none", **kw)
    gen = torch.Generator().manual_seed(11)
    b = d2.perturb(x0, levels=torch.tensor(40), generator=gen)
    delta = torch.randn(b.target.shape, generator=gen, dtype=F64)
    sig = float(d2.schedule.sigmas[40])
    # per component: translation errors divided by (2σ)², rotation errors by (σ/2)²
    err = delta.square() * torch.tensor([0.5] * 3 + [3.0] * 3, dtype=F64)
    expected = (err / torch.tensor([2 * sig] * 3 + [0.5 * sig] * 3, dtype=F64) ** 2).sum(-1).mean()
    assert_close(d0.loss(b.target + delta, b), expected, rtol=1e-12, atol=0)
    # with unit scales and a single level the two weightings differ by exactly σ²
    e2, e0 = make("se3"), make("se3", weighting="none")
    b = e2.perturb(x0, levels=torch.tensor(40), generator=gen)
    assert_close(e0.loss(b.target + delta, b), e2.loss(b.target + delta, b) / sig**2, rtol=1e-12, atol=0)


@pytest.mark.parametrize("group_name", ["so3", "r3so3", "se3", "se2"])
def test_rotation_and_translation_weights(group_name: str) -> None:
    g = get_group(group_name)
    rot = torch.zeros(g.dim, dtype=torch.bool)
    rot[g.rotation_slice] = True
    x0 = clean(group_name, 4)
    base = make(group_name)
    b = base.perturb(x0, generator=torch.Generator().manual_seed(12))
    delta = torch.ones_like(b.target)
    d_rot = (delta * rot).square().sum(-1).mean()
    d_tr = (delta * ~rot).square().sum(-1).mean()
    weighted = make(group_name, rotation_weight=3.0, translation_weight=0.25)
    assert_close(weighted.loss(b.target + delta, b), 3.0 * d_rot + 0.25 * d_tr)
    # an error in the rotation part only is blind to the translation weight, and vice versa
    assert_close(weighted.loss(b.target + delta * rot, b), 3.0 * d_rot)
    if not bool(rot.all()):
        assert_close(weighted.loss(b.target + delta * ~rot, b), 0.25 * d_tr)


def test_loss_shape_mismatch() -> None:
    d = make("se3")
    b = d.perturb(clean("se3", 4), generator=torch.Generator().manual_seed(13))
    with pytest.raises(ValueError, match="output"):
        d.loss(b.target[..., :3], b)


# ----------------------------------------------------------------------------- priors
def _wrapped_chi3_mean_angle(sigma: float) -> float:
    """E[angle of Exp(z)], z ~ N(0, σ²I₃): the radius is σ·χ₃ and the angle folds into [0, π]."""
    x, w = np.polynomial.legendre.leggauss(400)
    top = 12 * sigma
    r, w = (x + 1) / 2 * top, w * top / 2
    density = math.sqrt(2 / math.pi) * r**2 * np.exp(-(r**2) / (2 * sigma**2)) / sigma**3
    angle = np.abs(np.mod(r + np.pi, 2 * np.pi) - np.pi)
    return float((density * angle * w).sum())


def _haar_ks(angle: torch.Tensor) -> float:
    """Kolmogorov–Smirnov distance to the Haar angle law, density (1 − cos θ)/π, CDF (θ − sin θ)/π."""
    a = angle.sort().values
    n = a.shape[0]
    cdf = (a - a.sin()) / math.pi
    hi = torch.arange(1, n + 1, dtype=a.dtype) / n
    return float(torch.maximum((cdf - hi).abs(), (cdf - (hi - 1 / n)).abs()).max())


def _angles(x: torch.Tensor) -> torch.Tensor:
    return SO3().log(x[..., :3, :3].contiguous()).norm(dim=-1)


@pytest.mark.parametrize("group_name", ["so3", "se3"])
def test_kernel_prior_is_concentrated_at_identity(group_name: str) -> None:
    d = make(group_name, prior="kernel")
    x = d.prior((20000,), generator=torch.Generator().manual_seed(14), dtype=F64)
    assert x.shape == (20000, d.group.matrix_dim, d.group.matrix_dim) and x.dtype == F64
    d.group.check(x)
    expected = _wrapped_chi3_mean_angle(d.schedule.sigma_max)  # ≈ 1.5615 for σ_max = 0.98507
    assert float(_angles(x).mean()) == pytest.approx(expected, abs=0.02)
    assert _haar_ks(_angles(x)) > 0.2  # clearly not Haar (Haar mean angle is π/2 + 2/π ≈ 2.207)


@pytest.mark.parametrize("group_name", ["so3", "se3"])
def test_haar_prior_rotation_is_uniform(group_name: str) -> None:
    d = make(group_name, prior="haar")
    x = d.prior((20000,), generator=torch.Generator().manual_seed(15), dtype=F64)
    d.group.check(x)
    assert _haar_ks(_angles(x)) < 0.03
    # axes are uniform too: the mean rotation vector direction is ≈ 0
    phi = SO3().log(x[..., :3, :3].contiguous())
    assert float((phi / phi.norm(dim=-1, keepdim=True)).mean(0).norm()) < 0.03
    if group_name == "se3":  # translation from the kernel at σ_max: spread, unbounded
        t = x[..., :3, 3]
        assert 0.5 < float(t.std()) < 2.0


def test_haar_prior_on_se2_keeps_the_kernel_translation() -> None:
    d = make("se2", prior="haar")
    x = d.prior((20000,), generator=torch.Generator().manual_seed(18), dtype=F64)
    d.group.check(x)
    theta = torch.atan2(x[..., 1, 0], x[..., 0, 0])
    assert float(theta.min()) < -3.1 and float(theta.max()) > 3.1  # uniform rotation angle
    # the kernel's translation at σ_max ≈ 0.985 is unbounded (the kernel prior reaches |t| > 4)
    assert float(x[..., :2, 2].abs().max()) > 1.5


def test_uniform_prior_translation_in_box() -> None:
    d = make("se3", prior="uniform", prior_bound=2.5)
    x = d.prior((20000,), generator=torch.Generator().manual_seed(16), dtype=F64)
    d.group.check(x)
    t = x[..., :3, 3]
    assert float(t.abs().max()) <= 2.5
    assert float(t.min()) < -2.45 and float(t.max()) > 2.45
    assert float(t.std()) == pytest.approx(2.5 / math.sqrt(3), rel=0.03)
    assert _haar_ks(_angles(x)) < 0.03


def test_prior_determinism_and_batch_shape() -> None:
    for prior in ("kernel", "haar", "uniform"):
        d = make("se3", prior=prior)
        a = d.prior((2, 3), generator=torch.Generator().manual_seed(17), dtype=torch.float32)
        b = d.prior((2, 3), generator=torch.Generator().manual_seed(17), dtype=torch.float32)
        assert a.shape == (2, 3, 4, 4) and a.dtype == torch.float32
        assert torch.equal(a, b)


# ----------------------------------------------------------------------------- configuration errors
@pytest.mark.parametrize(
    ("kw", "options"),
    [
        ({"output": "eps"}, "score, noise"),
        ({"loss": "l1"}, "tangent_l2, chordal"),
        ({"prior": "gauss"}, "kernel, haar, uniform"),
        ({"weighting": "sigma"}, "sigma2, none"),
    ],
)
def test_invalid_names(kw: dict, options: str) -> None:
    with pytest.raises(ValueError, match=options):
        make("se3", **kw)


def test_unknown_score_target() -> None:
    with pytest.raises(KeyError, match="autograd, closed_form, surrogate"):
        make("se3", score="exact")


def test_chordal_rejects_unweighted() -> None:
    with pytest.raises(ValueError, match="weighting"):
        make("se3", loss="chordal", weighting="none")


def test_describe() -> None:
    d = make("se3", score="closed_form", output="noise", prior="haar")
    desc = d.describe()
    assert desc["group"] == "se3" and desc["score"] == "closed_form" and desc["output"] == "noise"
    assert desc["prior"] == "haar" and desc["num_levels"] == 100
    assert desc["sigma_max"] == pytest.approx(0.98507, abs=5e-6)
    assert isinstance(SE3(), type(d.group))
