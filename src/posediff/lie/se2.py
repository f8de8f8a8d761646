"""SE(2): planar rigid motions, ``(*b, 3, 3)`` ``[[R, t], [0, 1]]``, tangent ``[ρx, ρy, θ]``.

The worked example of adding a manifold (see "How to add a group" in docs/extending.md): one class,
kernels written with the shared coefficient functions, and the contract suite does the rest.
Closed forms (Solà et al. 2018, Sec. IV-A/Appendix C), with A, B, C, D from ``_numerics``:

* Exp(ρ, θ) = (R(θ), V(θ) ρ),  V = [[A, −θB], [θB, A]]
* Log: θ = atan2(R₁₀, R₀₀),  ρ = V⁻¹ t,  V⁻¹ = [[α, θ/2], [−θ/2, α]],  α = (θ/2) cot(θ/2) = 1 − θ²D
* J_l = [[A, −θB, θCρ₁ + Bρ₂], [θB, A, −Bρ₁ + θCρ₂], [0, 0, 1]],  J_r(ξ) = J_l(−ξ)
"""

import math

import torch
from torch import Tensor

from ._numerics import Angle
from ._pose import make_pose, pose_act, pose_error, pose_inverse, project_pose, split_pose
from .base import LieGroup


def _rot2(cos: Tensor, sin: Tensor) -> Tensor:
    return torch.stack([cos, -sin, sin, cos], dim=-1).unflatten(-1, (2, 2))


def _rows3(entries: list[Tensor]) -> Tensor:
    return torch.stack(entries, dim=-1).unflatten(-1, (3, 3))


class SE2(LieGroup, name="se2"):
    """Rigid motions in the plane: elements ``(*b, 3, 3)``, tangent ``[ρx, ρy, θ]``."""

    dim = 3
    matrix_dim = 3
    rotation_slice = slice(2, 3)
    point_dim = 2

    @classmethod
    def _exp(cls, xi: Tensor) -> Tensor:
        r1, r2, th = xi.unbind(-1)
        ang = Angle(th * th)
        a, tb = ang.A(), th * ang.B()
        R = _rot2(1.0 - th * tb, th * a)  # cos θ = 1 − θ²B, sin θ = θA
        t = torch.stack([a * r1 - tb * r2, tb * r1 + a * r2], dim=-1)
        return make_pose(R, t)

    @classmethod
    def _log(cls, g: Tensor) -> Tensor:
        R, t = split_pose(g)
        th = torch.atan2(R[..., 1, 0], R[..., 0, 0])
        alpha = 1.0 - th * th * Angle(th * th).D()
        h = 0.5 * th
        tx, ty = t.unbind(-1)
        return torch.stack([alpha * tx + h * ty, -h * tx + alpha * ty, th], dim=-1)

    @classmethod
    def _inverse(cls, g: Tensor) -> Tensor:
        return pose_inverse(g)

    @classmethod
    def _act(cls, g: Tensor, p: Tensor) -> Tensor:
        return pose_act(g, p)

    @classmethod
    def _hat(cls, xi: Tensor) -> Tensor:
        r1, r2, th = xi.unbind(-1)
        o = torch.zeros_like(th)
        return _rows3([o, -th, r1, th, o, r2, o, o, o])

    @classmethod
    def _vee(cls, X: Tensor) -> Tensor:
        th = 0.5 * (X[..., 1, 0] - X[..., 0, 1])
        return torch.stack([X[..., 0, 2], X[..., 1, 2], th], dim=-1)

    @classmethod
    def _adjoint(cls, g: Tensor) -> Tensor:
        R, t = split_pose(g)
        c, s = R[..., 0, 0], R[..., 1, 0]
        tx, ty = t.unbind(-1)
        o, i = torch.zeros_like(c), torch.ones_like(c)
        return _rows3([c, -s, ty, s, c, -tx, o, o, i])

    @classmethod
    def _jac_left(cls, xi: Tensor) -> Tensor:
        r1, r2, th = xi.unbind(-1)
        ang = Angle(th * th)
        a, b, tb, tc = ang.A(), ang.B(), th * ang.B(), th * ang.C()
        o, i = torch.zeros_like(th), torch.ones_like(th)
        return _rows3([a, -tb, tc * r1 + b * r2, tb, a, -b * r1 + tc * r2, o, o, i])

    @classmethod
    def _jac_left_inv(cls, xi: Tensor) -> Tensor:
        r1, r2, th = xi.unbind(-1)
        ang = Angle(th * th)
        b, tc = ang.B(), th * ang.C()
        alpha, h = 1.0 - th * th * ang.D(), 0.5 * th
        m1, m2 = tc * r1 + b * r2, -b * r1 + tc * r2  # last column of J_l
        o, i = torch.zeros_like(th), torch.ones_like(th)
        # [[V, m], [0, 1]]⁻¹ = [[V⁻¹, −V⁻¹ m], [0, 1]]
        return _rows3([alpha, h, -(alpha * m1 + h * m2), -h, alpha, -(-h * m1 + alpha * m2), o, o, i])

    @classmethod
    def _project(cls, m: Tensor) -> Tensor:
        return project_pose(m)

    @classmethod
    def _element_error(cls, g: Tensor) -> Tensor:
        return pose_error(g)

    @classmethod
    def _sample_uniform(cls, shape, generator, device, dtype, bound):  # type: ignore[no-untyped-def]
        u = torch.rand(*shape, 3, generator=generator, device=device, dtype=dtype)
        th = (2.0 * u[..., 2] - 1.0) * math.pi
        return make_pose(_rot2(torch.cos(th), torch.sin(th)), (2.0 * u[..., :2] - 1.0) * bound)
