"""Rotation-angle coefficient functions, exact in float64 and stable in float32 at θ = 0 and θ = π.

Every function takes ``theta2 = θ²`` (a tensor; never θ itself, so that nothing takes the square
root of zero) and returns a coefficient that appears in the closed forms of Exp, Log and the
Jacobians. Below ``SMALL_THETA2`` a Taylor series in θ² is used (enough terms for float64
round-off at the threshold), above it the closed form written with half-angle sines, which has no
cancellation in ``1 - cos θ``. Both branches are computed on *safe* inputs so that neither
produces inf/NaN, which would otherwise leak into gradients through ``torch.where``.

Names (θ = |φ|):

=====  ================================  ====================================================
 name   value                             where it appears
=====  ================================  ====================================================
 A      sin θ / θ                         Exp (Rodrigues)
 B      (1 − cos θ) / θ²                  Exp, J_l, J_r, SE(3) translation V = J_l(φ)
 C      (θ − sin θ) / θ³                  J_l, J_r, V
 D      (1 − (θ/2) cot(θ/2)) / θ²         J_l⁻¹, J_r⁻¹, SE(3) Log
 E      (θ² + 2 cos θ − 2) / (2 θ⁴)       the Q block of the SE(3) Jacobian (paper supp. Eq. q_def)
 F      (2θ − 3 sin θ + θ cos θ) / (2θ⁵)  the Q block of the SE(3) Jacobian
=====  ================================  ====================================================
"""

import math
from fractions import Fraction

import torch
from torch import Tensor

#: θ² below which the Taylor branch is used. At θ = 0.5 the series below reach float64 round-off.
SMALL_THETA2 = 0.25
_TERMS = 12


def _bernoulli(n_max: int) -> list[Fraction]:
    """Bernoulli numbers B_0..B_n_max (B_1 = -1/2 convention), exact."""
    b = [Fraction(0)] * (n_max + 1)
    for m in range(n_max + 1):
        b[m] = Fraction(1)
        if m:
            b[m] = -sum((math.comb(m + 1, k) * b[k] for k in range(m)), Fraction(0)) / (m + 1)
    return b


_B = _bernoulli(2 * _TERMS + 2)
_f = math.factorial

# Coefficients c_j of Σ_j c_j (θ²)^j.
_SERIES: dict[str, tuple[float, ...]] = {
    "A": tuple((-1) ** j / _f(2 * j + 1) for j in range(_TERMS)),
    "B": tuple((-1) ** j / _f(2 * j + 2) for j in range(_TERMS)),
    "C": tuple((-1) ** j / _f(2 * j + 3) for j in range(_TERMS)),
    "D": tuple(float((-1) ** j * _B[2 * j + 2] / _f(2 * j + 2)) for j in range(_TERMS)),
    "E": tuple((-1) ** j / _f(2 * j + 4) for j in range(_TERMS)),
    "F": tuple((-1) ** j * (j + 1) / _f(2 * j + 5) for j in range(_TERMS)),
    # arcsin(s)/s in s², used by the SO(3) Log near the identity.
    "asin": tuple(_f(2 * j) / (4**j * _f(j) ** 2 * (2 * j + 1)) for j in range(_TERMS)),
}


def series(name: str, x: Tensor, terms: int = _TERMS) -> Tensor:
    """Horner evaluation of the named Taylor series at ``x`` (θ² or s²)."""
    coeffs = _SERIES[name][:terms]
    out = torch.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


class Angle:
    """θ-dependent pieces shared by several coefficients, computed once per θ² tensor."""

    __slots__ = ("theta2", "small", "t2", "theta", "sin_half", "cos_half")

    def __init__(self, theta2: Tensor) -> None:
        self.theta2 = theta2
        self.small = theta2 < SMALL_THETA2
        # Safe θ² for the closed-form branch (never 0): the small branch does not use it.
        self.t2 = torch.where(self.small, torch.ones_like(theta2), theta2)
        self.theta = self.t2.sqrt()
        half = 0.5 * self.theta
        self.sin_half = torch.sin(half)
        self.cos_half = torch.cos(half)

    def _pick(self, name: str, closed: Tensor) -> Tensor:
        return torch.where(self.small, series(name, self.theta2), closed)

    def sin(self) -> Tensor:
        return 2.0 * self.sin_half * self.cos_half

    def one_minus_cos(self) -> Tensor:
        return 2.0 * self.sin_half * self.sin_half

    def A(self) -> Tensor:
        return self._pick("A", self.sin() / self.theta)

    def B(self) -> Tensor:
        return self._pick("B", self.one_minus_cos() / self.t2)

    def C(self) -> Tensor:
        return self._pick("C", (self.theta - self.sin()) / (self.t2 * self.theta))

    def D(self) -> Tensor:
        # (θ/2) cot(θ/2) written with the half-angle sine: finite at θ = π, singular at θ = 2π.
        half_cot = 0.5 * self.theta * self.cos_half / self.sin_half
        return self._pick("D", (1.0 - half_cot) / self.t2)

    def E(self) -> Tensor:
        return self._pick("E", (0.5 * self.t2 - self.one_minus_cos()) / (self.t2 * self.t2))

    def F(self) -> Tensor:
        s = self.sin()
        cos = 1.0 - self.one_minus_cos()
        num = 2.0 * self.theta - 3.0 * s + self.theta * cos
        return self._pick("F", num / (2.0 * self.t2 * self.t2 * self.theta))


def safe_sqrt(x: Tensor) -> Tensor:
    """√x with a zero (not NaN/inf) gradient at x = 0."""
    positive = x > 0
    return torch.where(positive, torch.where(positive, x, torch.ones_like(x)).sqrt(), torch.zeros_like(x))
