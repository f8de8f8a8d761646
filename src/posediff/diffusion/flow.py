"""Flow matching on the group: the samplers of a flow model and the exact velocity of a known target.

A model trained with ``Diffusion(objective="flow")`` (:mod:`posediff.diffusion.process`) outputs the
body velocity ``u(X, t)`` of the flow that carries the prior (t = 0: Haar rotation × Gaussian
translation) onto the data (t = 1) along geodesics, ``dX/dt = X · u^``. Sampling integrates that
ODE from a prior draw, every update a right multiplication ``X · Exp(·)`` so the samples stay on the
group; the network is called with the noise level :meth:`Diffusion.flow_sigma` ``(t)`` stands for.

Samplers (their grid, :meth:`FlowSampler.sigma_grid`, is of *times* ``t_j → t_{j+1}`` from 0 to 1):

* ``flow_euler`` — ``X ← X · Exp(h · u(X, t))`` (one network evaluation per step);
* ``flow_heun`` — the Crouch–Grossman form of Heun's method (order 2): ``k₁ = u(X, t)``,
  ``k₂ = u(X · Exp(h k₁), t + h)``, ``X ← X · Exp(½h k₁) · Exp(½h k₂)``; the last step, which lands on
  t = 1 where the velocity of a concentrated law is singular, is an Euler step
  (``2n − 1`` evaluations for ``n`` steps).

Time grids (``spacing``): ``"uniform"`` ``t_j = j/n``; ``"cosine"`` ``t_j = ½(1 − cos(π j/n))``, denser
at both ends. ``rotation_rate`` c > 0 is FrameFlow's faster rotation schedule (Yim et al. 2023): a
step covers the fraction ``(κ(t+h) − κ(t)) / (1 − κ(t))`` of the *remaining* rotation, with
``κ(t) = (1 − e^{−ct}) / (1 − e^{−c})``, instead of ``h / (1 − t)`` (c → 0 is the plain step); the
translation keeps the linear schedule. The remaining displacement is ``(1 − t) u``, so the plain step
is ``h u``.

:class:`FlowOracle` is the exact marginal velocity of a weighted mixture of point masses,
``E[u | X_t] = Σ_k π_k(X_t) u_k`` with ``u_k = Log(X_t⁻¹C_k)/(1 − t)`` and ``π_k ∝ w_k p_t(X_t | C_k)``,
``p_t(X_t | C_k) = p₀(C_k · Exp(−u_k)) · |J(u_k)| / ((1 − t)^d |J((1 − t) u_k)|)`` (the change of
variables of ``X_t = C_k · Exp(−(1 − t) u)`` from ``X₀ = C_k · Exp(−u)``; ``|J|`` the Jacobian
determinant of Exp, the Haar density in exponential coordinates), zero where ``u_k``'s rotation
leaves the principal ball (|φ| ≥ π; a pose outside every support, where a start on a cut locus that
rides its support's boundary lands after a rounding error, follows the nearest) — what the samplers
are tested with, the analogue of
:class:`~posediff.diffusion.MixtureOracle`.
"""

import math
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from .likelihood import prior_log_prob
from .oracle import mixture_log_weights
from .process import Diffusion
from .samplers import DenoiseFn, Sampler

SPACINGS = ("uniform", "cosine")


class FlowSampler(Sampler):
    """Base class of the flow samplers: the time grid and the network's velocity.

    Args:
        spacing: ``"uniform"`` or ``"cosine"`` times (module docstring).
        rotation_rate: FrameFlow's rotation schedule rate c (0: the plain linear schedule).
    """

    objective: ClassVar[str] = "flow"
    few_nfe: ClassVar[bool] = True
    #: network evaluations per step (the last step takes one)
    stages: ClassVar[int] = 1

    def __init__(
        self,
        diffusion: Diffusion,
        *,
        num_steps: int | None = None,
        spacing: Literal["uniform", "cosine"] = "uniform",
        rotation_rate: float = 0.0,
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps)
        if spacing not in SPACINGS:
            raise ValueError(f"{self.name}: unknown spacing {spacing!r}; options: {', '.join(SPACINGS)}")
        if not (math.isfinite(float(rotation_rate)) and float(rotation_rate) >= 0.0):
            raise ValueError(f"{self.name}: rotation_rate must be ≥ 0, got {rotation_rate}")
        self.spacing = spacing
        self.rotation_rate = float(rotation_rate)

    def network_calls(self, num_steps: int) -> int:
        return self.stages * (num_steps - 1) + 1

    def sigma_grid(self, num_steps: int | None = None) -> tuple[Tensor, Tensor]:
        """The flow's *times* ``(t_j, t_{j+1})``, float64 ``(num_steps,)`` each, from 0 to 1 (the last
        ``t_{j+1}`` is 1). Default steps: the schedule's number of levels."""
        n = int(num_steps if num_steps is not None else self.diffusion.schedule.num_levels)
        i = torch.arange(n + 1, dtype=torch.float64) / n
        t = i if self.spacing == "uniform" else 0.5 * (1.0 - torch.cos(math.pi * i))
        return t[:-1], t[1:]

    def velocity(self, denoise_fn: DenoiseFn, x: Tensor, t: float, cond: Any) -> Tensor:
        """The network's body velocity ``u(X, t)``, ``(*b, dim)``."""
        sigma = self.diffusion.flow_sigma(torch.full(x.shape[:-2], t, dtype=x.dtype, device=x.device))
        out = denoise_fn(x, sigma.to(x.dtype), cond)
        if out.shape != (*x.shape[:-2], self.group.dim):
            raise ValueError(
                f"denoise_fn returned {tuple(out.shape)}; expected {(*x.shape[:-2], self.group.dim)}"
            )
        return out

    def advance(self, x: Tensor, u: Tensor, t: float, t_next: float) -> Tensor:
        """``X · Exp(δ)``: the step from t to t_next along velocity ``u`` — ``δ = (t_next − t) u``, the
        rotation part rescaled by FrameFlow's schedule when ``rotation_rate > 0``."""
        h = t_next - t
        if self.rotation_rate <= 0.0:
            return self.group.rplus(x, h * u)
        c = self.rotation_rate
        kappa = lambda s: (1.0 - math.exp(-c * s)) / (1.0 - math.exp(-c))  # noqa: E731
        remaining = 1.0 - t
        frac_rot = (kappa(t_next) - kappa(t)) / max(1.0 - kappa(t), 1e-12)
        scale = torch.full((self.group.dim,), h, dtype=u.dtype, device=u.device)
        scale[self.group.rotation_slice] = frac_rot * remaining
        return self.group.rplus(x, scale * u)

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        raise NotImplementedError


class FlowEulerSampler(FlowSampler, name="flow_euler"):
    """Euler on the group: ``X ← X · Exp(h · u(X, t))`` (module docstring).

    ``fresh_prior=True`` is the flow's analogue of ``few_step_renoise``: each step predicts the clean pose
    ``X̂₁ = X · Exp((1 − t) u)`` and re-draws the noise, ``X ← X₀' · Exp(t' · Log(X₀'⁻¹ X̂₁))`` with a
    fresh prior pose ``X₀'`` (the interpolant's own law at t' around X̂₁, as in multistep consistency
    sampling); the step onto t = 1 is ``X̂₁``. One network evaluation per step, as Euler; not a
    discretisation of the ODE (``rotation_rate`` does not apply to it).
    """

    def __init__(
        self,
        diffusion: Diffusion,
        *,
        num_steps: int | None = None,
        spacing: Literal["uniform", "cosine"] = "uniform",
        rotation_rate: float = 0.0,
        fresh_prior: bool = False,
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps, spacing=spacing, rotation_rate=rotation_rate)
        self.fresh_prior = bool(fresh_prior)

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        u = self.velocity(denoise_fn, x, sigma_t, cond)
        if not self.fresh_prior:
            return self.advance(x, u, sigma_t, sigma_p)
        g = self.group
        x1 = g.rplus(x, (1.0 - sigma_t) * u)  # the clean pose the velocity points at
        if sigma_p >= 1.0:
            return x1
        x0 = self.diffusion.prior(tuple(x.shape[:-2]), generator=generator, dtype=x.dtype, device=x.device)
        return g.rplus(x0, sigma_p * g.rminus(x0, x1))


class FlowHeunSampler(FlowSampler, name="flow_heun"):
    """Crouch–Grossman Heun (order 2) on the flow's time grid; the step onto t = 1 is Euler."""

    stages: ClassVar[int] = 2

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        k1 = self.velocity(denoise_fn, x, sigma_t, cond)
        euler = self.advance(x, k1, sigma_t, sigma_p)
        if sigma_p >= 1.0:
            return euler
        k2 = self.velocity(denoise_fn, euler, sigma_p, cond)
        half = 0.5 * (sigma_t + sigma_p)
        return self.advance(self.advance(x, k1, sigma_t, half), k2, half, sigma_p)


class FlowOracle:
    """``denoise_fn`` of the exact flow velocity for a mixture of point masses (``centers (K, n, n)``
    or per input ``(B, K, n, n)``; ``weights (K,)`` or ``(B, K)``, default uniform) — module docstring.

    Args:
        diffusion: a flow diffusion (its prior and ``flow_sigma`` define the flow).
        t_max: times above it are read as ``t_max`` (the velocity of a point mass is singular at 1).
    """

    def __init__(
        self,
        diffusion: Diffusion,
        centers: Tensor,
        weights: Tensor | None = None,
        *,
        t_max: float = 1.0 - 1e-6,
    ) -> None:
        if diffusion.objective != "flow":
            raise ValueError("FlowOracle needs Diffusion(objective='flow'); MixtureOracle is the score's")
        self.diffusion = diffusion
        self.centers = centers
        self.log_weights = mixture_log_weights(centers, weights)
        self.t_max = float(t_max)

    def time(self, sigma: Tensor) -> Tensor:
        """The flow time a noise level stands for (the inverse of ``flow_sigma``)."""
        sched = self.diffusion.schedule
        return 1.0 - sched.level(sigma).to(torch.float64) / (sched.num_levels - 1)

    def __call__(self, x: Tensor, sigma: Tensor, cond: Any = None) -> Tensor:
        d = self.diffusion
        g = d.group
        c = self.centers.to(x.dtype)
        if c.ndim == 3:
            c = c.expand(x.shape[0], *c.shape)
        t = self.time(sigma).clamp(0.0, self.t_max).to(x.dtype)  # (B, N)
        one_minus = (1.0 - t).unsqueeze(-1)  # (B, N, 1)
        v = g.rminus(x.unsqueeze(2), c.unsqueeze(1))  # Log(X_t⁻¹ C_k): (B, N, K, dim)
        u = v / one_minus.unsqueeze(-1)
        x0 = g.rplus(c.unsqueeze(1), -u)  # C_k · Exp(−u_k)
        log_p = prior_log_prob(d, x0) + _log_jac(g, u) - _log_jac(g, v) - g.dim * torch.log(one_minus)
        ratio = u[..., g.rotation_slice].norm(dim=-1)  # the start's distance from C_k, in (0, π) inside
        log_p = torch.where(ratio < math.pi, log_p, torch.full_like(log_p, -math.inf))
        logw = self.log_weights.to(x.dtype)
        logw = logw.expand(x.shape[0], -1) if logw.ndim == 1 else logw
        resp = torch.softmax(log_p + logw.unsqueeze(1), dim=-1)
        # A start on a cut locus (|u_k| = π) rides its support's boundary to C_k; a step's rounding can put
        # it just outside every support, where the law has no mass: it belongs to the nearest support.
        outside = ~torch.isfinite(log_p).any(-1, keepdim=True)
        nearest = torch.nn.functional.one_hot(ratio.argmin(-1), ratio.shape[-1]).to(resp.dtype)
        resp = torch.where(outside, nearest, torch.nan_to_num(resp, nan=0.0))
        return (resp.unsqueeze(-1) * u).sum(-2)


def _log_jac(g: Any, xi: Tensor) -> Tensor:
    """``log |det J_r(ξ)|``: the Haar density of Exp in exponential coordinates (even in ξ)."""
    return torch.linalg.slogdet(g.jac_right(xi))[1]


__all__ = ["FlowSampler", "FlowEulerSampler", "FlowHeunSampler", "FlowOracle", "SPACINGS"]
