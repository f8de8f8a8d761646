"""SO(3): rotations as ``(*b, 3, 3)`` matrices, tangent φ ∈ R³ (rotation vector).

Closed forms (Solà et al. 2018; paper supplement "Left and Right Jacobians on SO(3)"), with
θ = |φ| and K = φ× (the skew matrix):

* Exp(φ) = I + A K + B K²                  (Rodrigues)
* J_l(φ) = I + B K + C K²,   J_r(φ) = J_l(−φ) = J_l(φ)ᵀ        (paper Eq. 9)
* J_l⁻¹(φ) = I − ½ K + D K²,  J_r⁻¹(φ) = I + ½ K + D K²
* Log(R): θ = atan2(|v|, (tr R − 1)/2) with v = vee(R − Rᵀ)/2 = sin θ · axis. For θ < π/2 it
  returns v θ / sin θ (a series in sin²θ near 0); for θ ≥ π/2 the axis comes from the symmetric
  part ``(R + Rᵀ)/2 − cos θ I = (1 − cos θ) a aᵀ``, which keeps every digit up to and at θ = π,
  with the sign taken from v.

The helpers in this module are shared by R3SO3, SE3 and the score code.
"""

import torch
from torch import Tensor

from ._numerics import Angle, safe_sqrt, series
from .base import LieGroup

#: below this sin²θ (and θ < π/2) the Log uses the arcsin(s)/s series
_LOG_SMALL_S2 = 1e-6


def skew(v: Tensor) -> Tensor:
    """``(*b, 3)`` → ``(*b, 3, 3)`` with ``skew(v) @ w = v × w``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).unflatten(-1, (3, 3))


def unskew(m: Tensor) -> Tensor:
    """``(*b, 3, 3)`` → ``(*b, 3)``, the vee of the antisymmetric part."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], dim=-1
    )


def quadratic_form(phi: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``I + a K + b K²`` with K = φ×, written entrywise (K² = φφᵀ − θ² I); ``a``, ``b`` are ``(*b,)``."""
    x, y, z = phi.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    entries = [
        1.0 - b * (yy + zz), bxy - az, bxz + ay,
        bxy + az, 1.0 - b * (xx + zz), byz - ax,
        bxz - ay, byz + ax, 1.0 - b * (xx + yy),
    ]  # fmt: skip
    return torch.stack(entries, dim=-1).unflatten(-1, (3, 3))


def theta2_of(phi: Tensor) -> Tensor:
    """|φ|², written out (faster than a reduction on a trailing dim of 3)."""
    x, y, z = phi.unbind(-1)
    return x * x + y * y + z * z


def exp_so3(phi: Tensor) -> Tensor:
    ang = Angle(theta2_of(phi))
    return quadratic_form(phi, ang.A(), ang.B())


def left_jacobian_so3(phi: Tensor) -> Tensor:
    ang = Angle(theta2_of(phi))
    return quadratic_form(phi, ang.B(), ang.C())


def left_jacobian_inv_so3(phi: Tensor) -> Tensor:
    ang = Angle(theta2_of(phi))
    return quadratic_form(phi, torch.full_like(ang.theta2, -0.5), ang.D())


def log_so3(R: Tensor) -> Tensor:
    """Principal rotation vector of ``R``; exact to round-off for every angle including π."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R.flatten(-2).unbind(-1)
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
    phi_small = torch.stack([vx, vy, vz], dim=-1) * factor.unsqueeze(-1)

    # θ ≥ π/2: a aᵀ = ((R + Rᵀ)/2 − c I) / (1 − c); take the row with the largest diagonal.
    d = torch.where(near_pi, 1.0 - c, torch.ones_like(c))
    b00, b11, b22 = (r00 - c) / d, (r11 - c) / d, (r22 - c) / d
    b01, b02, b12 = 0.5 * (r01 + r10) / d, 0.5 * (r02 + r20) / d, 0.5 * (r12 + r21) / d
    k0 = (b00 >= b11) & (b00 >= b22)
    k1 = ~k0 & (b11 >= b22)
    k2 = ~(k0 | k1)
    one = torch.ones_like(c)
    n0 = torch.where(k0 & near_pi, b00, one).sqrt()
    n1 = torch.where(k1 & near_pi, b11, one).sqrt()
    n2 = torch.where(k2 & near_pi, b22, one).sqrt()
    ax = torch.where(k0, b00 / n0, torch.where(k1, b01 / n1, b02 / n2))
    ay = torch.where(k0, b01 / n0, torch.where(k1, b11 / n1, b12 / n2))
    az = torch.where(k0, b02 / n0, torch.where(k1, b12 / n1, b22 / n2))
    sign = torch.where(ax * vx + ay * vy + az * vz < 0.0, -one, one)
    phi_pi = torch.stack([ax, ay, az], dim=-1) * (sign * theta).unsqueeze(-1)

    return torch.where(near_pi.unsqueeze(-1), phi_pi, phi_small)


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
    q = torch.randn(*shape, 4, generator=generator, device=device, dtype=dtype)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    entries = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(entries, dim=-1).unflatten(-1, (3, 3))


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
