"""R3SO3: the direct product R³ × SO(3), stored like SE3 as ``(*b, 4, 4)`` ``[[R, t], [0, 1]]``.

Composition is ``(R₂, t₂)(R₁, t₁) = (R₂R₁, t₂ + t₁)`` (paper Sec. 3.1): translation and rotation
diffuse independently, ``Exp(ρ, φ) = (Exp(φ), ρ)``. Because this product is *not* the 4×4 matmul,
``matrix_rep`` maps an element to the faithful 7×7 block-diagonal matrix
``diag(R, [[I, t], [0, 1]])`` for the oracle checks. Jacobians are block-diagonal,
``J_l = diag(I, J_l(φ)) = J_rᵀ`` (paper Eq. 8, 10), so the score is exactly −z/σ² (paper Eq. 9–10).
"""

import torch
from torch import Tensor

from ._pose import (
    block_matrix,
    make_pose,
    pose_act,
    pose_entries,
    pose_error,
    pose_from_entries,
    pose_hat,
    pose_vee,
    project_pose,
    split_pose,
    uniform_pose,
)
from .base import LieGroup
from .so3 import (
    exp_so3_entries,
    left_jacobian_inv_so3,
    left_jacobian_so3,
    log_so3,
    log_so3_entries,
    matmul3,
    skew,
)


class R3SO3(LieGroup, name="r3so3"):
    """Translation and rotation as a direct product: elements ``(*b, 4, 4)``, tangent ``[ρ, φ]``."""

    dim = 6
    matrix_dim = 4
    rotation_slice = slice(3, 6)

    @classmethod
    def _exp(cls, xi: Tensor) -> Tensor:
        e = xi.unbind(-1)
        return pose_from_entries(exp_so3_entries(e[3:]), e[:3])  # type: ignore[arg-type]

    @classmethod
    def _log(cls, g: Tensor) -> Tensor:
        R, t = pose_entries(g)
        return torch.stack([*t, *log_so3_entries(R)], dim=-1)

    @classmethod
    def _compose(cls, g: Tensor, h: Tensor) -> Tensor:
        Rg, tg = pose_entries(g)
        Rh, th = pose_entries(h)
        if torch.compiler.is_compiling():  # entrywise: one fused kernel instead of a batched GEMM
            R = matmul3(Rg, Rh)
        else:
            R = tuple((g[..., :3, :3] @ h[..., :3, :3]).flatten(-2).unbind(-1))
        return pose_from_entries(R, (tg[0] + th[0], tg[1] + th[1], tg[2] + th[2]))

    @classmethod
    def _inverse(cls, g: Tensor) -> Tensor:
        R, t = split_pose(g)
        return make_pose(R.mT, -t)

    @classmethod
    def _rminus(cls, g: Tensor, h: Tensor) -> Tensor:
        Rg, tg = split_pose(g)
        Rh, th = split_pose(h)
        return torch.cat([th - tg, log_so3(Rg.mT @ Rh)], dim=-1)

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
        R, _ = split_pose(g)
        return _blockdiag_eye(R)

    @classmethod
    def _jac_left(cls, xi: Tensor) -> Tensor:
        return _blockdiag_eye(left_jacobian_so3(xi[..., 3:]))

    @classmethod
    def _jac_left_inv(cls, xi: Tensor) -> Tensor:
        return _blockdiag_eye(left_jacobian_inv_so3(xi[..., 3:]))

    @classmethod
    def _project(cls, m: Tensor) -> Tensor:
        return project_pose(m)

    @classmethod
    def _element_error(cls, g: Tensor) -> Tensor:
        return pose_error(g)

    @classmethod
    def _sample_uniform(cls, shape, generator, device, dtype, bound):  # type: ignore[no-untyped-def]
        return uniform_pose(shape, generator, device, dtype, bound)

    def matrix_rep(self, g: Tensor) -> Tensor:
        """The faithful 7×7 representation ``diag(R, [[I, t], [0, 1]])``."""
        R, t = split_pose(self._element(g, "matrix_rep"))
        eye = torch.eye(3, dtype=g.dtype, device=g.device).expand_as(R)
        return _blockdiag(R, make_pose(eye, t))

    def algebra_rep(self, xi: Tensor) -> Tensor:
        """``diag(φ×, [[0, ρ], [0, 0]])``, the algebra of ``matrix_rep``."""
        xi = self._tangent(xi, "algebra_rep")
        W = skew(xi[..., 3:])
        top = torch.cat([torch.zeros_like(W), xi[..., :3].unsqueeze(-1)], dim=-1)
        return _blockdiag(W, torch.cat([top, torch.zeros_like(top[..., :1, :])], dim=-2))


def _blockdiag(a: Tensor, b: Tensor) -> Tensor:
    za = a.new_zeros(*a.shape[:-1], b.shape[-1])
    zb = b.new_zeros(*b.shape[:-1], a.shape[-1])
    return block_matrix([[a, za], [zb, b]])


def _blockdiag_eye(M: Tensor) -> Tensor:
    """``diag(I₃, M)`` for ``M (*b, 3, 3)``."""
    return _blockdiag(torch.eye(3, dtype=M.dtype, device=M.device).expand_as(M), M)
