"""Score targets, ``posediff.diffusion.stein_score``: surrogate (Eq. 12), closed form (Eq. 5), autograd (Eq. 18).

Why the three agree on SO3 and R3SO3 but not on SE3 (tangent ``z = [ρ, φ]``):

* The closed form is ``−J_r⁻ᵀ(z) z / σ²``; the surrogate is ``−z/σ²``. They are equal iff ``J_rᵀ(z) z = z``.
* SO3: ``J_rᵀ(φ) = J_r(−φ) = J_l(φ)`` and ``J_l(φ) φ = φ``, so they always agree (Eq. 8–9). R3SO3 is
  block diagonal ``diag(I, J_r(φ))``, so the same holds (Eq. 10).
* SE3: ``J_r(z) = [[J(φ), Q(ρ, φ)], [0, J(φ)]]`` with ``J = J_r^{SO3}``, hence
  ``J_rᵀ z = [J(φ)ᵀ ρ, Q(ρ, φ)ᵀ ρ + J(φ)ᵀ φ] = [J(φ)ᵀ ρ, Q(ρ, φ)ᵀ ρ + φ]``.
  ``J(φ)ᵀ ρ = ρ + a φ×ρ + b φ×(φ×ρ)`` with ``a ≠ 0`` for ``0 < |φ| < 2π``, so the first block equals ``ρ``
  iff ``ρ × φ = 0``. When ``ρ = λφ`` every term of ``Q`` is a polynomial in ``[φ]×`` with at least one factor
  ``[φ]×``, so ``Qᵀ ρ = λ Qᵀ φ = 0``. Therefore ``J_r⁻ᵀ(z) z = z`` **iff ``ρ × φ = 0``** (``ρ ∥ φ``, ``ρ = 0``
  or ``φ = 0``), and the difference is first order in ``ρ × φ``. ``test_se3_equality_iff_rho_parallel_phi``
  checks each step numerically.
"""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import ConcentratedGaussian, stein_score
from posediff.lie import SE2, SE3, get_group

METHODS = ("surrogate", "closed_form", "autograd")
F64 = torch.float64


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def random_tangent(group_name: str, n: int, seed: int, *, max_angle: float = math.pi - 0.05) -> torch.Tensor:
    """``n`` float64 tangents with rotation angles uniform in (0.05, max_angle) and N(0, 1) translations."""
    gen = torch.Generator().manual_seed(seed)
    group = get_group(group_name)
    z = torch.randn(n, group.dim, generator=gen, dtype=F64)
    sl = group.rotation_slice
    k = sl.stop - sl.start
    axis = _unit(torch.randn(n, k, generator=gen, dtype=F64)) if k > 1 else torch.ones(n, 1, dtype=F64)
    angle = 0.05 + (max_angle - 0.05) * torch.rand(n, 1, generator=gen, dtype=F64)
    z[:, sl] = axis * angle
    return z


SIGMAS = [0.05, 0.7, 2.0, "per_sample"]


def _sigma(spec: float | str, n: int) -> torch.Tensor | float:
    if spec == "per_sample":
        return torch.linspace(0.01, 1.5, n, dtype=F64)
    return float(spec)


def _expected_surrogate(z: torch.Tensor, sigma: torch.Tensor | float) -> torch.Tensor:
    sig = torch.as_tensor(sigma, dtype=F64)
    return -z / (sig.unsqueeze(-1) if sig.ndim else sig) ** 2


# ----------------------------------------------------------------------------- SO3 / R3SO3: all agree
@pytest.mark.parametrize("group_name", ["so3", "r3so3"])
@pytest.mark.parametrize("sigma_spec", SIGMAS)
def test_all_targets_agree_on_so3_and_r3so3(group_name: str, sigma_spec: float | str) -> None:
    z = random_tangent(group_name, 64, seed=1)
    sigma = _sigma(sigma_spec, 64)
    expected = _expected_surrogate(z, sigma)
    for method in METHODS:
        s = stein_score(group_name, z, sigma, method)
        assert s.shape == z.shape and s.dtype == F64
        assert_close(s, expected, rtol=1e-9, atol=1e-9 / (0.01**2), msg=method)


@pytest.mark.parametrize("group_name", ["so3", "r3so3"])
def test_closed_form_equals_surrogate_near_pi(group_name: str) -> None:
    z = random_tangent(group_name, 32, seed=2, max_angle=math.pi - 1e-6)
    sl = get_group(group_name).rotation_slice
    z[:, sl] = _unit(z[:, sl]) * (math.pi - 1e-6)
    assert_close(stein_score(group_name, z, 0.3, "closed_form"), stein_score(group_name, z, 0.3, "surrogate"))


# ----------------------------------------------------------------------------- SE3: exact ≠ surrogate
@pytest.mark.parametrize("sigma_spec", SIGMAS)
def test_se3_closed_form_equals_autograd(sigma_spec: float | str) -> None:
    z = random_tangent("se3", 64, seed=3)
    sigma = _sigma(sigma_spec, 64)
    cf = stein_score("se3", z, sigma, "closed_form")
    ag = stein_score("se3", z, sigma, "autograd")
    scale = cf.abs().amax(-1, keepdim=True)
    assert_close(cf / scale, ag / scale, rtol=0, atol=1e-10)


def test_se3_closed_form_is_minus_jr_inverse_transpose_z() -> None:
    """Eq. 5 against an independent linear solve with ``J_r`` (not the closed-form ``J_r⁻¹``)."""
    z = random_tangent("se3", 32, seed=4)
    jr = SE3().jac_right(z)
    expected = -torch.linalg.solve(jr.transpose(-1, -2), z.unsqueeze(-1)).squeeze(-1) / 0.4**2
    assert_close(stein_score("se3", z, 0.4, "closed_form"), expected, rtol=1e-10, atol=1e-10)


def _coupled_se3(n: int, seed: int) -> torch.Tensor:
    """``z = [ρ, φ]`` with |φ| = 1 and the angle between ρ and φ in [45°, 135°], |ρ| in [0.5, 2]."""
    gen = torch.Generator().manual_seed(seed)
    phi = _unit(torch.randn(n, 3, generator=gen, dtype=F64))
    perp = _unit(torch.linalg.cross(phi, torch.randn(n, 3, generator=gen, dtype=F64)))
    alpha = math.pi / 4 + math.pi / 2 * torch.rand(n, 1, generator=gen, dtype=F64)
    length = 0.5 + 1.5 * torch.rand(n, 1, generator=gen, dtype=F64)
    rho = length * (alpha.cos() * phi + alpha.sin() * perp)
    return torch.cat([rho, phi], -1)


def test_se3_exact_score_differs_from_surrogate_when_coupled() -> None:
    z = _coupled_se3(256, seed=5)
    for sigma in (0.1, 1.0):
        sur = stein_score("se3", z, sigma, "surrogate")
        for method in ("closed_form", "autograd"):
            exact = stein_score("se3", z, sigma, method)
            rel = (exact - sur).norm(dim=-1) / sur.norm(dim=-1)
            assert bool((rel > 1e-2).all()), f"{method}: min relative difference {float(rel.min()):.3g}"
            # not a small effect either: the median sample is tens of percent off
            assert float(rel.median()) > 0.1


@pytest.mark.parametrize("case", ["parallel", "antiparallel", "pure_translation", "pure_rotation"])
def test_se3_targets_agree_when_uncoupled(case: str) -> None:
    gen = torch.Generator().manual_seed(6)
    n = 64
    phi = _unit(torch.randn(n, 3, generator=gen, dtype=F64)) * (
        0.1 + 2.9 * torch.rand(n, 1, generator=gen, dtype=F64)
    )
    lam = 0.2 + 2 * torch.rand(n, 1, generator=gen, dtype=F64)
    rho = {
        "parallel": lam * phi,
        "antiparallel": -lam * phi,
        "pure_translation": torch.randn(n, 3, generator=gen, dtype=F64),
        "pure_rotation": torch.zeros(n, 3, dtype=F64),
    }[case]
    if case == "pure_translation":
        phi = torch.zeros_like(phi)
    z = torch.cat([rho, phi], -1)
    sur = stein_score("se3", z, 0.5, "surrogate")
    assert_close(stein_score("se3", z, 0.5, "closed_form"), sur, rtol=1e-10, atol=1e-10)
    assert_close(stein_score("se3", z, 0.5, "autograd"), sur, rtol=1e-9, atol=1e-9)


def test_se3_equality_iff_rho_parallel_phi() -> None:
    """The derivation in the module docstring, step by step: ``J_rᵀ z − z`` is first order in ``ρ × φ``."""
    gen = torch.Generator().manual_seed(7)
    phi = _unit(torch.randn(16, 3, generator=gen, dtype=F64)) * 1.3
    perp = _unit(torch.linalg.cross(phi, torch.randn(16, 3, generator=gen, dtype=F64)))
    jr = SE3().jac_right

    def defect(eps: float) -> torch.Tensor:
        z = torch.cat([0.8 * phi + eps * perp, phi], -1)
        return ((jr(z).transpose(-1, -2) @ z.unsqueeze(-1)).squeeze(-1) - z).norm(dim=-1)

    assert float(defect(0.0).max()) < 1e-12
    d1, d2 = defect(1e-5), defect(2e-5)
    assert bool((d1 > 1e-7).all())
    assert_close(d2 / d1, torch.full_like(d1, 2.0), rtol=1e-3, atol=0)
    # J_r z = z always (the defect is from the transpose, not from J_r itself)
    z = _coupled_se3(16, seed=8)
    assert_close((jr(z) @ z.unsqueeze(-1)).squeeze(-1), z, rtol=1e-12, atol=1e-12)


def test_se2_closed_form_equals_autograd() -> None:
    gen = torch.Generator().manual_seed(9)
    z = torch.randn(32, 3, generator=gen, dtype=F64)
    z[:, 2] = (torch.rand(32, generator=gen, dtype=F64) * 2 - 1) * (math.pi - 0.05)
    cf = stein_score(SE2(), z, 0.3, "closed_form")
    assert_close(cf, stein_score(SE2(), z, 0.3, "autograd"), rtol=1e-9, atol=1e-9)


# ----------------------------------------------------------------------------- API details
def test_unknown_method_lists_the_registered_ones() -> None:
    z = torch.zeros(2, 3)
    with pytest.raises(KeyError, match="autograd, closed_form, surrogate"):
        stein_score("so3", z, 0.1, "bogus")


def test_default_method_is_surrogate() -> None:
    z = random_tangent("se3", 8, seed=10)
    assert_close(stein_score("se3", z, 0.3), stein_score("se3", z, 0.3, "surrogate"))


@pytest.mark.parametrize("group_name", ["so3", "r3so3", "se3"])
@pytest.mark.parametrize("where", ["zero", "near_pi"])
def test_targets_finite_in_float32(group_name: str, where: str) -> None:
    group = get_group(group_name)
    z = torch.zeros(3, group.dim)
    if where == "near_pi":
        z[:, group.rotation_slice] = torch.tensor([[1.0, 0, 0], [0.6, 0.8, 0], [0, 0, -1.0]]) * (
            math.pi - 1e-6
        )
        if group.dim == 6:
            z[:, :3] = torch.tensor([[0.3, -0.2, 0.5], [1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    for method in METHODS:
        ref = stein_score(group_name, z.double(), 0.3, method)
        zz = z.clone().requires_grad_(True)
        s = stein_score(group_name, zz, 0.3, method)
        assert s.dtype == torch.float32 and bool(torch.isfinite(s).all()), method
        assert_close(s.double(), ref, rtol=1e-4, atol=1e-3, msg=method)
        if method == "autograd":
            # a constant regression target: computed from z.detach(), no graph back to z
            assert not s.requires_grad
            continue
        (grad,) = torch.autograd.grad(s.square().sum(), zz)
        assert bool(torch.isfinite(grad).all()), method


@pytest.mark.parametrize("group_name", ["so3", "r3so3", "se3"])
def test_per_component_scales(group_name: str) -> None:
    group = get_group(group_name)
    kernel = ConcentratedGaussian(group, translation_scale=2.0, rotation_scale=0.5)
    z = random_tangent(group_name, 32, seed=11)
    sigma = torch.linspace(0.1, 1.0, 32, dtype=F64)
    sigma_c = torch.full((32, group.dim), 2.0, dtype=F64) * sigma[:, None]
    sigma_c[:, group.rotation_slice] = 0.5 * sigma[:, None]
    expected = -z / sigma_c**2
    assert_close(stein_score(group, z, sigma, "surrogate", kernel=kernel), expected, rtol=1e-12, atol=0)
    cf = stein_score(group, z, sigma, "closed_form", kernel=kernel)
    ag = stein_score(group, z, sigma, "autograd", kernel=kernel)
    assert_close(cf, ag, rtol=1e-9, atol=1e-8)
    if group_name != "se3":
        assert_close(cf, expected, rtol=1e-10, atol=1e-8)
    else:
        assert not torch.allclose(cf, expected, rtol=1e-3)


def test_kernel_on_another_group_is_rejected() -> None:
    with pytest.raises(ValueError, match="kernel is on"):
        stein_score("se3", torch.zeros(6), 0.1, kernel=ConcentratedGaussian("r3so3"))
