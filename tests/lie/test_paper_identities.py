"""Identities from the paper (Hsiao et al., CVPR 2024) and its supplement, checked numerically.

* Eq. 8:  J_l(z) = J_r(z)ᵀ and J_l⁻¹(z) = J_r⁻ᵀ(z) on SO(3) and R³×SO(3).
* Eq. 9–10: hence the closed-form score J_r⁻ᵀ(z) (−z/σ²) equals the surrogate −z/σ², i.e. J_r⁻ᵀ(z) z = z.
* Eq. 11: on SE(3), J_r⁻ᵀ(z) ≠ J_l⁻¹(z) for coupled motions, and J_r⁻ᵀ(z) z ≠ z.
* Supplement: Q(−ρ, −φ)ᵀ = Q(ρ, φ), and J_r⁻ᵀ(z) = [[J_l⁻¹(φ), 0], [Z, J_l⁻¹(φ)]] with
  Z = −J_l⁻¹(φ) Q(ρ, φ) J_l⁻¹(φ).

Plus the relations between R3SO3, SE3 and SE2 that follow from their definitions.
All in float64.
"""

import math

import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.lie import R3SO3, SE2, SE3, SO3, LieGroup
from posediff.lie.se3 import q_block
from posediff.testing import oracle_jacobians, tangents_at_angles

F64 = torch.float64
TINY = [0.0, 1e-12, 1e-8, 1e-6, 1e-4]
NEAR_PI = [math.pi - 1e-3, math.pi - 1e-5, math.pi - 1e-7, math.pi]


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _angles(n: int, seed: int, low: float = 0.05, high: float = 3.0) -> list[float]:
    u = torch.rand(n, generator=_gen(seed), dtype=F64)
    return (low + (high - low) * u).tolist()


def _mv(M: Tensor, v: Tensor) -> Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _coupled(angles: list[float], seed: int) -> Tensor:
    """SE(3) tangents whose translation has a unit component orthogonal to φ (never parallel)."""
    xi = tangents_at_angles(SE3(), angles, seed=seed)
    phi = xi[:, 3:]
    axis = phi / phi.norm(dim=-1, keepdim=True)
    r = torch.randn(len(angles), 3, generator=_gen(seed + 1000), dtype=F64)
    perp = torch.linalg.cross(axis, r)
    perp = perp / perp.norm(dim=-1, keepdim=True)
    xi[:, :3] = perp + 0.5 * torch.randn(len(angles), 1, generator=_gen(seed + 2000), dtype=F64) * axis
    return xi


# ------------------------------------------------------------------------------ Eq. 8–10
@pytest.mark.parametrize("group", [SO3(), R3SO3()], ids=lambda g: g.name)
def test_eq9_left_jacobian_is_right_transposed(group: LieGroup) -> None:
    z = tangents_at_angles(group, TINY + _angles(32, seed=1) + NEAR_PI, seed=2)
    assert_close(group.jac_left(z), group.jac_right(z).mT, atol=1e-13, rtol=0.0)
    assert_close(group.jac_left_inv(z), group.jac_right_inv(z).mT, atol=1e-13, rtol=0.0)
    # and they are what they claim to be: J_r⁻¹ is the inverse of J_r
    eye = torch.eye(group.dim, dtype=F64).expand(z.shape[0], -1, -1)
    assert_close(group.jac_right_inv(z) @ group.jac_right(z), eye, atol=1e-11, rtol=0.0)


@pytest.mark.parametrize("group", [SO3(), R3SO3()], ids=lambda g: g.name)
def test_eq10_closed_form_score_is_the_surrogate(group: LieGroup) -> None:
    """J_r⁻ᵀ(z) (−z/σ²) = −z/σ²: the closed-form score reduces to the surrogate."""
    z = tangents_at_angles(group, TINY + _angles(32, seed=3) + NEAR_PI, seed=4, trans_scale=2.0)
    sigma = 0.37
    score = _mv(group.jac_right_inv(z).mT, -z / sigma**2)
    assert_close(score, -z / sigma**2, atol=1e-11, rtol=1e-12)
    assert_close(_mv(group.jac_right_inv(z).mT, z), z, atol=1e-12, rtol=1e-12)


# ------------------------------------------------------------------------------ Eq. 11 (SE3)
def test_eq13_se3_coupled_motion_breaks_the_identity() -> None:
    z = _coupled(_angles(32, seed=5, low=0.3), seed=6)
    jrit, jli = SE3().jac_right_inv(z).mT, SE3().jac_left_inv(z)
    gap = (jrit - jli).abs().flatten(-2).amax(-1)
    assert float(gap.min()) > 1e-3, f"J_r^-T(z) == J_l^-1(z) on a coupled motion (gap {float(gap.min()):.2e})"
    score_gap = (_mv(jrit, z) - z).norm(dim=-1)
    assert float(score_gap.min()) > 1e-3, "J_r^-T(z) z == z on a coupled motion"


def test_eq13_se3_pure_rotation_and_translation() -> None:
    """Pure rotations: J_r⁻ᵀ = J_l⁻¹ exactly (Q(0, φ) = 0). Pure translations: the score identity
    J_r⁻ᵀ(z) z = z still holds, but the *matrices* differ — Q(ρ, 0) = ½ρ×, so J_l⁻¹ has −½ρ× in
    its upper-right block while J_r⁻ᵀ has −½ρ× in its lower-left block."""
    rot = tangents_at_angles(SE3(), TINY + _angles(16, seed=7) + NEAR_PI, seed=8)
    rot[:, :3] = 0.0
    assert_close(SE3().jac_right_inv(rot).mT, SE3().jac_left_inv(rot), atol=1e-13, rtol=0.0)
    assert_close(_mv(SE3().jac_right_inv(rot).mT, rot), rot, atol=1e-12, rtol=0.0)

    trans = torch.randn(16, 6, generator=_gen(9), dtype=F64)
    trans[:, 3:] = 0.0
    jrit, jli = SE3().jac_right_inv(trans).mT, SE3().jac_left_inv(trans)
    assert_close(_mv(jrit, trans), trans, atol=1e-13, rtol=0.0)
    half_skew = 0.5 * SO3().hat(trans[:, :3])
    eye, zero = torch.eye(3, dtype=F64).expand(16, 3, 3), torch.zeros(16, 3, 3, dtype=F64)
    assert_close(
        jli,
        torch.cat([torch.cat([eye, -half_skew], -1), torch.cat([zero, eye], -1)], -2),
        atol=1e-15,
        rtol=0.0,
    )
    assert_close(
        jrit,
        torch.cat([torch.cat([eye, zero], -1), torch.cat([-half_skew, eye], -1)], -2),
        atol=1e-15,
        rtol=0.0,
    )


def test_supplement_block_structure_of_se3_jr_inv_transposed() -> None:
    """J_r⁻ᵀ(z) = [[J_l⁻¹(φ), 0], [Z, J_l⁻¹(φ)]], Z = −J_l⁻¹(φ) Q(ρ, φ) J_l⁻¹(φ), against the
    inverse of an autograd-through-matrix_exp J_r (independent of posediff's Jacobian code)."""
    z = torch.cat(
        [
            _coupled([1e-4, 0.3, 1.0, 2.0, 2.9, math.pi - 1e-3], seed=10),
            _coupled(_angles(4, seed=11), seed=12),
        ]
    )
    jr_oracle, jl_oracle = oracle_jacobians(SE3(), z)
    jrit = torch.linalg.inv(jr_oracle).mT
    rho, phi = z[:, :3], z[:, 3:]
    ji = SO3().jac_left_inv(phi)
    Z = -ji @ q_block(rho, phi) @ ji
    assert_close(jrit[:, :3, :3], ji, atol=1e-10, rtol=0.0)
    assert_close(jrit[:, 3:, 3:], ji, atol=1e-10, rtol=0.0)
    assert_close(jrit[:, :3, 3:], torch.zeros_like(ji), atol=1e-10, rtol=0.0)
    assert_close(jrit[:, 3:, :3], Z, atol=1e-10, rtol=0.0)
    assert float(Z.abs().amax(dim=(-2, -1)).min()) > 1e-3  # the block is genuinely there
    # posediff's own closed form agrees with the oracle
    assert_close(SE3().jac_right_inv(z).mT, jrit, atol=1e-10, rtol=0.0)
    # and Q is the upper-right block of the oracle J_l
    assert_close(q_block(rho, phi), jl_oracle[:, :3, 3:], atol=1e-10, rtol=0.0)


# ------------------------------------------------------------------------------ Q symmetry
def test_supplement_q_transpose_symmetry() -> None:
    """Q(−ρ, −φ)ᵀ = Q(ρ, φ) for random inputs, tiny angles and angles up to 3."""
    angles = TINY + [1e-3, 1e-2, 0.49, 0.5, 0.51] + _angles(32, seed=13, low=0.0, high=3.0) + [3.0]
    xi = tangents_at_angles(SE3(), angles, seed=14, trans_scale=3.0)
    rho, phi = xi[:, :3], xi[:, 3:]
    Q = q_block(rho, phi)
    assert_close(q_block(-rho, -phi).mT, Q, atol=1e-13, rtol=1e-13)
    # Q is not symmetric itself, so the identity is not vacuous
    assert float((Q - Q.mT).abs().amax(dim=(-2, -1)).min()) > 1e-2


# ------------------------------------------------------------------------------ R3SO3 vs SE3
def _pure(n: int, seed: int, kind: str) -> Tensor:
    xi = tangents_at_angles(SE3(), _angles(n, seed=seed) + NEAR_PI[:3], seed=seed + 1, trans_scale=2.0)
    if kind == "rotation":
        xi[:, :3] = 0.0
    else:
        xi[:, 3:] = 0.0
    return xi


def test_r3so3_and_se3_exp() -> None:
    for kind in ("rotation", "translation"):
        xi = _pure(16, seed=15, kind=kind)
        assert_close(R3SO3().exp(xi), SE3().exp(xi), atol=1e-15, rtol=0.0)
    xi = _coupled(_angles(16, seed=17, low=0.3), seed=18)
    a, b = R3SO3().exp(xi), SE3().exp(xi)
    assert_close(a[:, :3, :3], b[:, :3, :3], atol=1e-15, rtol=0.0)  # same rotation
    assert_close(a[:, :3, 3], xi[:, :3], atol=0.0, rtol=0.0)  # R3SO3: t = ρ
    # SE3: t = J_l(φ)ρ
    assert_close(b[:, :3, 3], _mv(SO3().jac_left(xi[:, 3:]), xi[:, :3]), atol=1e-14, rtol=0.0)
    gap = (a[:, :3, 3] - b[:, :3, 3]).norm(dim=-1)
    assert float(gap.min()) > 1e-2, "SE3 and R3SO3 exp agree on a coupled motion"


def test_r3so3_and_se3_compose() -> None:
    """(R₁, t₁)(R₂, t₂): SE3 gives t₁ + R₁t₂, R3SO3 gives t₁ + t₂."""
    g = SE3().sample_uniform((16,), generator=_gen(19), dtype=F64, bound=2.0)
    h = SE3().sample_uniform((16,), generator=_gen(20), dtype=F64, bound=2.0)
    eye = torch.eye(3, dtype=F64)
    left_translation = g.clone()
    left_translation[:, :3, :3] = eye  # R₁ = I
    assert_close(
        R3SO3().compose(left_translation, h), SE3().compose(left_translation, h), atol=1e-15, rtol=0.0
    )
    right_rotation = h.clone()
    right_rotation[:, :3, 3] = 0.0  # t₂ = 0
    assert_close(R3SO3().compose(g, right_rotation), SE3().compose(g, right_rotation), atol=1e-15, rtol=0.0)
    # in general they differ in the translation only
    a, b = R3SO3().compose(g, h), SE3().compose(g, h)
    assert_close(a[:, :3, :3], b[:, :3, :3], atol=1e-15, rtol=0.0)
    assert_close(a[:, :3, 3], g[:, :3, 3] + h[:, :3, 3], atol=1e-15, rtol=0.0)
    assert_close(b[:, :3, 3], g[:, :3, 3] + _mv(g[:, :3, :3], h[:, :3, 3]), atol=1e-15, rtol=0.0)
    assert float((a - b).abs().amax(dim=(-2, -1)).min()) > 1e-2


def test_r3so3_and_se3_log() -> None:
    for kind in ("rotation", "translation"):
        xi = _pure(16, seed=21, kind=kind)
        G = SE3().exp(xi)
        assert_close(R3SO3().log(G), SE3().log(G), atol=1e-13, rtol=0.0)
        assert_close(SE3().log(G), xi, atol=1e-10, rtol=0.0)
    xi = _coupled(_angles(16, seed=23, low=0.3), seed=24)
    G = SE3().exp(xi)
    a, b = R3SO3().log(G), SE3().log(G)
    assert_close(a[:, 3:], b[:, 3:], atol=1e-13, rtol=0.0)
    assert float((a[:, :3] - b[:, :3]).norm(dim=-1).min()) > 1e-2


# ------------------------------------------------------------------------------ SE2
def test_se2_zero_angle_is_pure_translation() -> None:
    rho = torch.randn(16, 2, generator=_gen(25), dtype=F64) * 3.0
    xi = torch.cat([rho, torch.zeros(16, 1, dtype=F64)], -1)
    G = SE2().exp(xi)
    expected = torch.eye(3, dtype=F64).repeat(16, 1, 1)
    expected[:, :2, 2] = rho
    assert_close(G, expected, atol=0.0, rtol=0.0)
    assert_close(SE2().log(G), xi, atol=1e-15, rtol=0.0)


def test_se2_is_planar_se3() -> None:
    """SE2 exp/log agree with SE3 on the embedded planar motion ρ = (ρx, ρy, 0), φ = (0, 0, θ)."""
    n = 32
    theta = torch.tensor(
        TINY + _angles(n - len(TINY) - 3, seed=26) + [math.pi - 1e-3, -2.0, -1e-6], dtype=F64
    )
    rho = torch.randn(n, 2, generator=_gen(27), dtype=F64) * 2.0
    xi2 = torch.cat([rho, theta[:, None]], -1)
    zero = torch.zeros(n, 1, dtype=F64)
    xi3 = torch.cat([rho, zero, zero, zero, theta[:, None]], -1)
    g2, g3 = SE2().exp(xi2), SE3().exp(xi3)
    assert_close(g2[:, :2, :2], g3[:, :2, :2], atol=1e-15, rtol=0.0)
    assert_close(g2[:, :2, 2], g3[:, :2, 3], atol=1e-14, rtol=0.0)
    # the SE3 motion stays in the plane
    assert_close(
        g3[:, 2, :], torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=F64).expand(n, 4), atol=1e-15, rtol=0.0
    )
    assert_close(g3[:, :2, 2], torch.zeros(n, 2, dtype=F64), atol=1e-15, rtol=0.0)
    log3 = SE3().log(g3)
    assert_close(SE2().log(g2), torch.cat([log3[:, :2], log3[:, 5:]], -1), atol=1e-12, rtol=0.0)
    assert_close(SE2().log(g2), xi2, atol=1e-10, rtol=0.0)
