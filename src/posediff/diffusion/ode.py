"""Deterministic samplers that integrate the probability-flow ODE on the group with integrators of order > 1.

The forward process ``X_σ = X · Exp(z)``, ``z ~ N(0, σ² diag(c²))`` has the probability-flow ODE
(Song et al., 2021; the one :mod:`posediff.diffusion.likelihood` integrates), right-trivialised::

    dX/dσ = X · v(X, σ)^,   v = −σ c² ⊙ s(X, σ) = c ⊙ ẑ(X, σ)

(``s`` the score of the network — paper Eq. 5/12 targets, ``ẑ = −σ c ⊙ s`` its unit-noise
estimate). Its flow carries the prior at σ_max onto the data law at σ → 0 with no noise drawn, so
a sampler is an ODE solver from σ_max down to the smallest level, then the clean prediction
``X · Exp(σ² s)`` (the Euler step to σ = 0, exact for a point mass with the surrogate target,
paper §4.3). Every update is a right multiplication ``X · Exp(·)``: the samples stay on the group.

Integrators (cost in network evaluations, NFE, for ``n`` steps: ``stages · (n − 1) + 1``):

* ``heun`` — the Crouch–Grossman form of Heun's method (order 2, 2 stages):
  ``X⁺ = X · Exp(½h k₁) · Exp(½h k₂)``, ``k₂`` at the Euler point ``X · Exp(h k₁)``.
* ``crouch_grossman`` — Crouch & Grossman's 3-stage scheme of order 3 (J. Nonlinear Sci. 1993):
  ``c = (0, 3/4, 17/24)``, ``a₂₁ = 3/4``, ``a₃₁ = 119/216``, ``a₃₂ = 17/108``,
  ``b = (13/51, −2/3, 24/17)``; each stage and the update a product of exponentials of frozen
  velocities.
* ``rkmk`` — Runge–Kutta–Munthe-Kaas with the classical RK4 tableau (order 4, 4 stages): the ODE
  is solved in the exponential coordinates ``u`` of ``X = X_n · Exp(u)``, where
  ``du/dσ = J_r(u)⁻¹ v(X_n · Exp(u), σ)`` (the group's exact right-Jacobian inverse).

Step sizes: ``spacing="schedule"`` visits the schedule's own levels (``timesteps``, as every other
sampler); ``"karras"`` the σ of Karras et al. (2022), ``σ_i = (σ_max^{1/ρ} + i/(n−1) (σ_min^{1/ρ} −
σ_max^{1/ρ}))^ρ`` (dense near the data for ρ > 1); ``"loglinear"`` geometric σ. Intermediate stages
query the network at σ between levels: posediff's networks read the continuous level
``schedule.level(σ)``.
"""

import math
from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from .process import Diffusion
from .samplers import DenoiseFn, Sampler

SPACINGS = ("schedule", "karras", "loglinear")


class ProbabilityFlowSampler(Sampler):
    """Base class of the ODE samplers: the σ grid, the velocity ``v = c ⊙ ẑ`` and the final clean step.

    Args:
        spacing: ``"schedule"`` (the schedule's levels), ``"karras"`` (ρ-spaced σ) or ``"loglinear"``.
        rho: the Karras exponent ρ (7 in Karras et al.).
    """

    few_nfe: ClassVar[bool] = True
    #: network evaluations per step (the last step, the clean prediction, takes one)
    stages: ClassVar[int]

    def __init__(
        self,
        diffusion: Diffusion,
        *,
        num_steps: int | None = None,
        spacing: Literal["schedule", "karras", "loglinear"] = "schedule",
        rho: float = 7.0,
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps)
        if spacing not in SPACINGS:
            raise ValueError(f"{self.name}: unknown spacing {spacing!r}; options: {', '.join(SPACINGS)}")
        if not float(rho) > 0:
            raise ValueError(f"{self.name}: rho must be > 0, got {rho}")
        self.spacing = spacing
        self.rho = float(rho)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_steps={self.num_steps}, spacing={self.spacing!r})"

    def network_calls(self, num_steps: int) -> int:
        return self.stages * (num_steps - 1) + 1

    def sigma_grid(self, num_steps: int | None = None) -> tuple[Tensor, Tensor]:
        if self.spacing == "schedule":
            return super().sigma_grid(num_steps)
        sched = self.diffusion.schedule
        n = sched.num_levels if num_steps is None else int(num_steps)
        lo, hi = sched.sigma_min, sched.sigma_max
        if n == 1:
            sig = torch.tensor([hi], dtype=torch.float64)
        elif self.spacing == "karras":
            r = 1.0 / self.rho
            i = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
            sig = (hi**r + i * (lo**r - hi**r)) ** self.rho
        else:
            sig = torch.logspace(math.log10(hi), math.log10(lo), n, dtype=torch.float64)
        if n > 1:  # exact end points (no rounding of the power / the logarithm)
            sig[0], sig[-1] = hi, lo
        return sig, torch.cat([sig[1:], sig.new_zeros(1)])

    def velocity(self, denoise_fn: DenoiseFn, x: Tensor, sigma: float, cond: Any) -> Tensor:
        """``v(X, σ) = −σ c² ⊙ s(X, σ)``: the right-trivialised ``dX/dσ``."""
        c2 = self.diffusion.kernel.scales(dtype=x.dtype, device=x.device) ** 2
        return -sigma * c2 * self.score(denoise_fn, x, sigma, cond)

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        if sigma_p == 0.0:  # the clean prediction X · Exp(σ² c² s) = the Euler step to σ = 0
            return self.group.rplus(x, -sigma_t * self.velocity(denoise_fn, x, sigma_t, cond))
        return self.ode_step(denoise_fn, x, sigma_t, sigma_p - sigma_t, cond)

    def ode_step(self, denoise_fn: DenoiseFn, x: Tensor, sigma: float, h: float, cond: Any) -> Tensor:
        """One step of the integrator from σ to σ + h (h < 0)."""
        raise NotImplementedError


def _product(group: Any, x: Tensor, terms: Sequence[tuple[float, Tensor]]) -> Tensor:
    """``X · Exp(a₁ k₁) · Exp(a₂ k₂) ⋯`` (zero coefficients skipped)."""
    for a, k in terms:
        if a != 0.0:
            x = group.rplus(x, a * k)
    return x


class HeunSampler(ProbabilityFlowSampler, name="heun"):
    """Heun's method on the group in Crouch–Grossman form (order 2, two evaluations per step)."""

    stages: ClassVar[int] = 2

    def ode_step(self, denoise_fn, x, sigma, h, cond):  # noqa: ANN001, ANN201
        k1 = self.velocity(denoise_fn, x, sigma, cond)
        k2 = self.velocity(denoise_fn, self.group.rplus(x, h * k1), sigma + h, cond)
        return _product(self.group, x, [(0.5 * h, k1), (0.5 * h, k2)])


class CrouchGrossmanSampler(ProbabilityFlowSampler, name="crouch_grossman"):
    """Crouch & Grossman's 3-stage, third-order commutator-free scheme (three evaluations per step)."""

    stages: ClassVar[int] = 3
    A: ClassVar[tuple[tuple[float, ...], ...]] = ((), (3 / 4,), (119 / 216, 17 / 108))
    B: ClassVar[tuple[float, ...]] = (13 / 51, -2 / 3, 24 / 17)
    C: ClassVar[tuple[float, ...]] = (0.0, 3 / 4, 17 / 24)

    def ode_step(self, denoise_fn, x, sigma, h, cond):  # noqa: ANN001, ANN201
        ks: list[Tensor] = []
        for a_row, c in zip(self.A, self.C, strict=True):
            y = _product(self.group, x, [(h * a, k) for a, k in zip(a_row, ks, strict=False)])
            ks.append(self.velocity(denoise_fn, y, sigma + c * h, cond))
        return _product(self.group, x, [(h * b, k) for b, k in zip(self.B, ks, strict=True)])


class RKMKSampler(ProbabilityFlowSampler, name="rkmk"):
    """Runge–Kutta–Munthe-Kaas with the classical RK4 tableau (order 4, four evaluations per step)."""

    stages: ClassVar[int] = 4

    def _coordinate_rate(
        self, denoise_fn: DenoiseFn, x: Tensor, u: Tensor, sigma: float, cond: Any
    ) -> Tensor:
        """``du/dσ = J_r(u)⁻¹ v(X · Exp(u), σ)``."""
        g = self.group
        v = self.velocity(denoise_fn, g.rplus(x, u), sigma, cond)
        return (g.jac_right_inv(u) @ v.unsqueeze(-1)).squeeze(-1)

    def ode_step(self, denoise_fn, x, sigma, h, cond):  # noqa: ANN001, ANN201
        k1 = self.velocity(denoise_fn, x, sigma, cond)  # J_r(0) = I
        k2 = self._coordinate_rate(denoise_fn, x, 0.5 * h * k1, sigma + 0.5 * h, cond)
        k3 = self._coordinate_rate(denoise_fn, x, 0.5 * h * k2, sigma + 0.5 * h, cond)
        k4 = self._coordinate_rate(denoise_fn, x, h * k3, sigma + h, cond)
        return self.group.rplus(x, (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4))
