"""SE(3): rigid motions as ``(*b, 4, 4)`` matrices ``[[R, t], [0, 1]]``, tangent ``[ρ, φ]``.

Semidirect product (paper Sec. 3.1): ``(R₂, t₂)(R₁, t₁) = (R₂R₁, t₂ + R₂t₁)`` and
``Exp(ρ, φ) = (Exp(φ), J_l(φ) ρ)``, so translation and rotation are coupled.

Jacobians with the Q block of the paper's supplement (Eq. q_def; Barfoot 2017, Eq. 7.86 — the
paper's typeset version mixes θ and θ², the form here is the one checked against autograd):

* J_l(ρ, φ) = [[J_l(φ), Q(ρ, φ)], [0, J_l(φ)]],   J_r(ρ, φ) = J_l(−ρ, −φ)
* J_l⁻¹(ρ, φ) = [[J_l⁻¹(φ), Z], [0, J_l⁻¹(φ)]],  Z = −J_l⁻¹(φ) Q(ρ, φ) J_l⁻¹(φ)
* Q(ρ, φ) = ½P + C (FP + PF + FPF) + E (F²P + PF² − 3FPF) + F' (FPF² + F²PF), with P = ρ×, F = φ×

Unlike SO3 and R3SO3, ``J_r⁻ᵀ(z) ≠ J_l⁻¹(z)`` on coupled motions (paper Eq. 11), which is why the
paper trains SE(3) with the surrogate score −z/σ² (Eq. 12).
"""

from typing import cast

import torch
from torch import Tensor

from ._numerics import Angle
from ._pose import (
    block_matrix,
    pose_act,
    pose_entries,
    pose_error,
    pose_from_entries,
    pose_hat,
    pose_inverse,
    pose_vee,
    project_pose,
    split_pose,
    uniform_pose,
)
from .base import LieGroup
from .so3 import (
    Vec3,
    cross,
    log_so3_entries,
    matmul3,
    matvec3,
    quadratic_entries,
    quadratic_form,
    skew,
    theta2_of,
)


def q_block(rho: Tensor, phi: Tensor) -> Tensor:
    """The Q(ρ, φ) block of the SE(3) left Jacobian, ``(*b, 3, 3)``."""
    ang = Angle(theta2_of(phi))
    c1, c2, c3 = ang.C(), ang.E(), ang.F()
    P, F = skew(rho), skew(phi)
    FP, PF = F @ P, P @ F
    FPF = FP @ F
    FFP, PFF = F @ FP, PF @ F
    FPFF, FFPF = FPF @ F, F @ FPF

    def s(c: Tensor) -> Tensor:
        return c[..., None, None]

    return 0.5 * P + s(c1) * (FP + PF + FPF) + s(c2) * (FFP + PFF - 3.0 * FPF) + s(c3) * (FPFF + FFPF)


class SE3(LieGroup, name="se3"):
    """Rigid motions in 3-D: elements ``(*b, 4, 4)``, tangent ``[ρ, φ]`` ``(*b, 6)``."""

    dim = 6
    matrix_dim = 4
    rotation_slice = slice(3, 6)

    @classmethod
    def _exp(cls, xi: Tensor) -> Tensor:
        e = xi.unbind(-1)
        rho, phi = cast(Vec3, e[:3]), cast(Vec3, e[3:])
        ang = Angle(theta2_of(phi))
        a, b, c = ang.A(), ang.B(), ang.C()
        w = cross(phi, rho)
        ww = cross(phi, w)
        # t = J_l(φ) ρ = ρ + B φ×ρ + C φ×(φ×ρ)
        t = tuple(rho[i] + b * w[i] + c * ww[i] for i in range(3))
        return pose_from_entries(quadratic_entries(phi, a, b), t)  # type: ignore[arg-type]

    @classmethod
    def _log(cls, g: Tensor) -> Tensor:
        R, t = pose_entries(g)
        phi = log_so3_entries(R)
        d = Angle(theta2_of(phi)).D()
        w = cross(phi, t)
        ww = cross(phi, w)
        # ρ = J_l⁻¹(φ) t = t − ½ φ×t + D φ×(φ×t)
        rho = [t[i] - 0.5 * w[i] + d * ww[i] for i in range(3)]
        return torch.stack([*rho, *phi], dim=-1)

    @classmethod
    def _compose(cls, g: Tensor, h: Tensor) -> Tensor:
        if torch.compiler.is_compiling():  # entrywise: one fused kernel instead of a batched GEMM
            Rg, tg = pose_entries(g)
            Rh, th = pose_entries(h)
            t = matvec3(Rg, th)
            return pose_from_entries(matmul3(Rg, Rh), (t[0] + tg[0], t[1] + tg[1], t[2] + tg[2]))
        return g @ h

    @classmethod
    def _inverse(cls, g: Tensor) -> Tensor:
        return pose_inverse(g)

    @classmethod
    def _act(cls, g: Tensor, p: Tensor) -> Tensor:
        return pose_act(g, p)

    @classmethod
    def _hat(cls, xi: Tensor) -> Tensor:
        return pose_hat(xi)

    @classmethod
    def _vee(cls, X: Tensor) -> Tensor:
        return pose_vee(X)

    @classmethod
    def _adjoint(cls, g: Tensor) -> Tensor:
        R, t = split_pose(g)
        return block_matrix([[R, skew(t) @ R], [torch.zeros_like(R), R]])

    @classmethod
    def _jac_left(cls, xi: Tensor) -> Tensor:
        rho, phi = xi[..., :3], xi[..., 3:]
        ang = Angle(theta2_of(phi))
        J = quadratic_form(phi, ang.B(), ang.C())
        return block_matrix([[J, q_block(rho, phi)], [torch.zeros_like(J), J]])

    @classmethod
    def _jac_left_inv(cls, xi: Tensor) -> Tensor:
        rho, phi = xi[..., :3], xi[..., 3:]
        ang = Angle(theta2_of(phi))
        Ji = quadratic_form(phi, torch.full_like(ang.theta2, -0.5), ang.D())
        Z = -Ji @ q_block(rho, phi) @ Ji
        return block_matrix([[Ji, Z], [torch.zeros_like(Ji), Ji]])

    @classmethod
    def _project(cls, m: Tensor) -> Tensor:
        return project_pose(m)

    @classmethod
    def _element_error(cls, g: Tensor) -> Tensor:
        return pose_error(g)

    @classmethod
    def _sample_uniform(cls, shape, generator, device, dtype, bound):  # type: ignore[no-untyped-def]
        return uniform_pose(shape, generator, device, dtype, bound)
