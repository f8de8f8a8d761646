"""SO(3): rotations as ``(*b, 3, 3)`` matrices, tangent φ ∈ R³ (rotation vector).

Closed forms (Solà et al. 2018; paper supplement "Left and Right Jacobians on SO(3)"), with
θ = |φ| and K = φ× (the skew matrix):

* Exp(φ) = I + A K + B K²                  (Rodrigues)
* J_l(φ) = I + B K + C K²,   J_r(φ) = J_l(−φ) = J_l(φ)ᵀ        (paper Eq. 8)
* J_l⁻¹(φ) = I − ½ K + D K²,  J_r⁻¹(φ) = I + ½ K + D K²
* Log(R): θ = atan2(|v|, (tr R − 1)/2) with v = vee(R − Rᵀ)/2 = sin θ · axis. For θ < π/2 it
  returns v θ / sin θ (a series in sin²θ near 0); for θ ≥ π/2 the axis comes from the symmetric
  part ``(R + Rᵀ)/2 − cos θ I = (1 − cos θ) a aᵀ``, which keeps every digit up to and at θ = π,
  with the sign taken from v.

The helpers in this module are shared by R3SO3, SE3 and the score code.
"""

from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor

from ._numerics import Angle, safe_sqrt, series
from .base import LieGroup

#: below this sin²θ (and θ < π/2) the Log uses the arcsin(s)/s series
_LOG_SMALL_S2 = 1e-6


Vec3 = tuple[Tensor, Tensor, Tensor]
#: a 3×3 matrix as its 9 entries, row-major
Mat3 = tuple[Tensor, ...]


def stack_entries(entries: Sequence[Tensor], rows: int, cols: int) -> Tensor:
    """Entries (row-major, broadcast against each other) → ``(*b, rows, cols)`` in one write."""
    return torch.stack(torch.broadcast_tensors(*entries), dim=-1).unflatten(-1, (rows, cols))


def skew(v: Tensor) -> Tensor:
    """``(*b, 3)`` → ``(*b, 3, 3)`` with ``skew(v) @ w = v × w``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return stack_entries([o, -z, y, z, o, -x, -y, x, o], 3, 3)


def unskew(m: Tensor) -> Tensor:
    """``(*b, 3, 3)`` → ``(*b, 3)``, the vee of the antisymmetric part."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], dim=-1
    )


def cross(a: Vec3, b: Vec3) -> Vec3:
    """``a × b`` on component tuples."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def matmul3(a: Mat3, b: Mat3) -> Mat3:
    """Product of two 3×3 matrices given as entry tuples (what ``torch.compile`` fuses best)."""
    return tuple(
        a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]
        for i in range(3)
        for j in range(3)
    )


def matvec3(a: Mat3, v: Vec3) -> Vec3:
    return (
        a[0] * v[0] + a[1] * v[1] + a[2] * v[2],
        a[3] * v[0] + a[4] * v[1] + a[5] * v[2],
        a[6] * v[0] + a[7] * v[1] + a[8] * v[2],
    )


def theta2_of(phi: Tensor | Vec3) -> Tensor:
    """|φ|², written out (faster than a reduction on a trailing dim of 3)."""
    x, y, z = phi.unbind(-1) if isinstance(phi, Tensor) else phi
    return x * x + y * y + z * z


def quadratic_entries(phi: Vec3, a: Tensor, b: Tensor) -> Mat3:
    """Entries of ``I + a K + b K²`` with K = φ× (K² = φφᵀ − θ² I); ``a``, ``b`` are ``(*b,)``."""
    x, y, z = phi
    xx, yy, zz = x * x, y * y, z * z
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    return (
        1.0 - b * (yy + zz), bxy - az, bxz + ay,
        bxy + az, 1.0 - b * (xx + zz), byz - ax,
        bxz - ay, byz + ax, 1.0 - b * (xx + yy),
    )  # fmt: skip


def quadratic_form(phi: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``I + a K + b K²`` as ``(*b, 3, 3)``."""
    return stack_entries(quadratic_entries(cast(Vec3, phi.unbind(-1)), a, b), 3, 3)


def exp_so3_entries(phi: Vec3) -> Mat3:
    ang = Angle(theta2_of(phi))
    return quadratic_entries(phi, ang.A(), ang.B())


def exp_so3(phi: Tensor) -> Tensor:
    return stack_entries(exp_so3_entries(cast(Vec3, phi.unbind(-1))), 3, 3)


def left_jacobian_so3(phi: Tensor) -> Tensor:
    ang = Angle(theta2_of(phi))
    return quadratic_form(phi, ang.B(), ang.C())


def left_jacobian_inv_so3(phi: Tensor) -> Tensor:
    ang = Angle(theta2_of(phi))
    return quadratic_form(phi, torch.full_like(ang.theta2, -0.5), ang.D())


def log_so3(R: Tensor) -> Tensor:
    """Principal rotation vector of ``R``; exact to round-off for every angle including π."""
    return torch.stack(log_so3_entries(tuple(R.flatten(-2).unbind(-1))), dim=-1)


def log_so3_entries(r: Mat3) -> Vec3:
    """``log_so3`` on the 9 entries of R (row-major), returning the 3 components of φ."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vx, vy, vz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    c = (0.5 * (r00 + r11 + r22 - 1.0)).clamp(-1.0, 1.0)
    s2 = vx * vx + vy * vy + vz * vz
    s = safe_sqrt(s2)
    theta = torch.atan2(s, c)

    near_pi = c < 0.0
    small = (s2 < _LOG_SMALL_S2) & ~near_pi
    # θ < π/2: φ = v · θ / sin θ; near 0 the same factor as a series in sin²θ.
    generic = ~(small | near_pi)
    s_safe = torch.where(generic, s, torch.ones_like(s))
    factor = torch.where(small, series("asin", s2, terms=5), theta / s_safe)

    # θ ≥ π/2: a aᵀ = ((R + Rᵀ)/2 − c I) / (1 − c); take the row k with the largest diagonal,
    # a = row_k / sqrt(diag_k). The common factor 1/(1 − c) cancels except in sqrt(diag_k).
    e00, e11, e22 = r00 - c, r11 - c, r22 - c
    e01, e02, e12 = 0.5 * (r01 + r10), 0.5 * (r02 + r20), 0.5 * (r12 + r21)
    k0 = (e00 >= e11) & (e00 >= e22)
    k1 = ~k0 & (e11 >= e22)
    ekk = torch.where(k0, e00, torch.where(k1, e11, e22))
    # (1 − c) · diag_k ≥ (1 − c)/3 ≥ 1/3 on this branch; elsewhere a safe dummy value.
    inv_norm = torch.where(near_pi, ekk * (1.0 - c), torch.ones_like(c)).rsqrt()
    ax = torch.where(k0, e00, torch.where(k1, e01, e02)) * inv_norm
    ay = torch.where(k0, e01, torch.where(k1, e11, e12)) * inv_norm
    az = torch.where(k0, e02, torch.where(k1, e12, e22)) * inv_norm
    scale = torch.where(ax * vx + ay * vy + az * vz < 0.0, -theta, theta)
    return (
        torch.where(near_pi, ax * scale, vx * factor),
        torch.where(near_pi, ay * scale, vy * factor),
        torch.where(near_pi, az * scale, vz * factor),
    )


def rotation_error(R: Tensor) -> Tensor:
    """Max violation of RᵀR = I and det R = 1 (any k×k), ``(*b,)``."""
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    ortho = (R.mT @ R - eye).abs().flatten(-2).amax(-1)
    return torch.maximum(ortho, (torch.linalg.det(R) - 1.0).abs())


def project_rotation(m: Tensor) -> Tensor:
    """The rotation nearest to ``m`` in Frobenius norm (SVD, with the determinant fixed)."""
    U, _, Vh = torch.linalg.svd(m)
    det = torch.linalg.det(U @ Vh)
    fix = torch.ones(m.shape[:-2] + (3,), dtype=m.dtype, device=m.device)
    fix = torch.cat([fix[..., :2], det.sign().unsqueeze(-1)], dim=-1)
    return (U * fix.unsqueeze(-2)) @ Vh


def uniform_rotation(
    shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device, dtype: torch.dtype
) -> Tensor:
    """Haar-uniform rotations: a normalised Gaussian quaternion, as a matrix."""
    return quaternion_matrix(torch.randn(*shape, 4, generator=generator, device=device, dtype=dtype))


def quaternion_matrix(q: Tensor) -> Tensor:
    """The rotation ``(*b, 3, 3)`` of quaternions ``q = (w, x, y, z)`` ``(*b, 4)``, normalised first (any
    non-zero scale; a standard-normal ``q`` gives a Haar-uniform rotation)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    entries = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return stack_entries(entries, 3, 3)


class SO3(LieGroup, name="so3"):
    """Rotations in 3-D: elements ``(*b, 3, 3)``, tangent φ ``(*b, 3)``."""

    dim = 3
    matrix_dim = 3
    rotation_slice = slice(0, 3)

    @classmethod
    def _exp(cls, xi: Tensor) -> Tensor:
        return exp_so3(xi)

    @classmethod
    def _log(cls, g: Tensor) -> Tensor:
        return log_so3(g)

    @classmethod
    def _compose(cls, g: Tensor, h: Tensor) -> Tensor:
        if torch.compiler.is_compiling():  # entrywise: one fused kernel instead of a batched GEMM
            return stack_entries(
                matmul3(tuple(g.flatten(-2).unbind(-1)), tuple(h.flatten(-2).unbind(-1))), 3, 3
            )
        return g @ h

    @classmethod
    def _inverse(cls, g: Tensor) -> Tensor:
        return g.mT.contiguous()

    @classmethod
    def _rminus(cls, g: Tensor, h: Tensor) -> Tensor:
        return log_so3(g.mT @ h)

    @classmethod
    def _act(cls, g: Tensor, p: Tensor) -> Tensor:
        return (g @ p.unsqueeze(-1)).squeeze(-1)

    @classmethod
    def _hat(cls, xi: Tensor) -> Tensor:
        return skew(xi)

    @classmethod
    def _vee(cls, X: Tensor) -> Tensor:
        return unskew(X)

    @classmethod
    def _adjoint(cls, g: Tensor) -> Tensor:
        return g.clone()

    @classmethod
    def _jac_left(cls, xi: Tensor) -> Tensor:
        return left_jacobian_so3(xi)

    @classmethod
    def _jac_left_inv(cls, xi: Tensor) -> Tensor:
        return left_jacobian_inv_so3(xi)

    @classmethod
    def _project(cls, m: Tensor) -> Tensor:
        return project_rotation(m)

    @classmethod
    def _element_error(cls, g: Tensor) -> Tensor:
        return rotation_error(g)

    @classmethod
    def _sample_uniform(cls, shape, generator, device, dtype, bound):  # type: ignore[no-untyped-def]
        return uniform_rotation(shape, generator, device, dtype)
