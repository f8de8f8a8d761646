"""Log-likelihood of a pose under a trained score model, by the probability-flow ODE on the group.

The forward process adds noise ``X_σ = X · Exp(z)``, ``z ~ N(0, σ² diag(c²))``. Its marginals ``p_σ``
are also transported by the deterministic *probability-flow ODE* (Song et al., 2021), written on
the group with a right-trivialised velocity::

    dX/dσ = X · v(X, σ)^,   v = −σ c² ⊙ s(X, σ) = c ⊙ ẑ(X, σ)

(``s`` the score, ``ẑ = −σ c ⊙ s`` the unit-noise estimate — the Euler step of this ODE is the
``few_step`` sampler). Along a trajectory the log density obeys ``d log p_σ(X(σ))/dσ = −div v``, so

    log p_{σ_min}(X) = log p_{σ_max}(X(σ_max)) + ∫_{σ_min}^{σ_max} div v(X(σ), σ) dσ.

``div`` is the divergence with respect to the Haar measure. SO(3), R³×SO(3) and SE(3) are
unimodular, so the left-invariant frame fields ``X·e_i^`` are divergence-free and
``div v = Σ_i ∂/∂τ_i v_i(X · Exp(τ))|_{τ=0}`` — the trace of the right-trivialised Jacobian of
``v``, computed exactly here with ``dim`` backward passes (no Hutchinson noise).

Assumptions (what the number means):

1. the network's score is the score of the noisy marginals ``p_σ`` (exact only for a perfectly
   trained model; the likelihood is that of the model's own ODE flow, which is a valid density
   whenever the prior term is);
2. ``p_{σ_max}`` is replaced by the sampler's prior (``Diffusion.prior``): the kernel at σ_max
   around the identity (``"kernel"``), Haar rotation × Gaussian translation (``"haar"``), or Haar ×
   uniform box (``"uniform"``) — a mismatch here shifts all poses' values by about the same amount;
3. the result is ``log p_{σ_min}``, the data law smoothed by the smallest noise level, as a density
   with respect to the Haar measure normalised to Lebesgue measure in exponential coordinates at
   the identity (SO(3) has volume 8π² in it; for SE(3)/R³×SO(3) it is that × Lebesgue on ``t``);
4. the ODE is integrated on ``num_steps`` log-spaced levels from σ_min to σ_max with a
   Crouch–Grossman/Heun step in ``log σ`` for ``X`` and the trapezoid rule (in ``log σ``) for the
   divergence — ``div v`` grows like ``dim/σ`` near the data, which ``log σ`` steps integrate well.

A flow model (``Diffusion(objective="flow")``) is its own ODE, ``dX/dt = X · u(X, t)^`` from the
prior (t = 0) to the data (t = 1), so ``log p₁(X) = log p₀(X(0)) − ∫₀¹ div u(X(t), t) dt``, integrated
backwards from ``t = flow_t_max`` (the network's last trained time) with Heun steps geometric in
``1 − t`` (``div u`` grows like ``−dim/(1 − t)`` near the data) and the prior's exact density.

Use it to *rank* poses: equivalent poses of a symmetric object get (nearly) equal values, poses off
the support far lower (``tests/diffusion/test_likelihood.py`` checks both with an exact oracle).
"""

import math
from typing import Any

import torch
from torch import Tensor

from .process import Diffusion
from .samplers import DenoiseFn


def _velocity(denoise_fn: DenoiseFn, diffusion: Diffusion, x: Tensor, sigma: float, cond: Any) -> Tensor:
    sig = torch.full(x.shape[:-2], sigma, dtype=x.dtype, device=x.device)
    score = diffusion.to_score(denoise_fn(x, sig, cond), sig)
    c2 = diffusion.kernel.scales(dtype=x.dtype, device=x.device) ** 2
    return -sigma * c2 * score


def _flow_velocity(denoise_fn: DenoiseFn, diffusion: Diffusion, x: Tensor, t: float, cond: Any) -> Tensor:
    sig = diffusion.flow_sigma(torch.full(x.shape[:-2], t, dtype=x.dtype, device=x.device)).to(x.dtype)
    return denoise_fn(x, sig, cond)


def _velocity_and_divergence(
    denoise_fn: DenoiseFn, diffusion: Diffusion, x: Tensor, sigma: float, cond: Any
) -> tuple[Tensor, Tensor]:
    """``(v, div v)`` at ``x``: the probability-flow velocity at level σ, or a flow model's at time σ."""
    g = diffusion.group
    field = _flow_velocity if diffusion.objective == "flow" else _velocity
    with torch.enable_grad():
        tau = torch.zeros((*x.shape[:-2], g.dim), dtype=x.dtype, device=x.device, requires_grad=True)
        v = field(denoise_fn, diffusion, g.rplus(x.detach(), tau), sigma, cond)
        div = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)
        for i in range(g.dim):
            (grad,) = torch.autograd.grad(v[..., i].sum(), tau, retain_graph=i < g.dim - 1)
            div = div + grad[..., i]
    return v.detach(), div.detach()


def prior_log_prob(diffusion: Diffusion, x: Tensor) -> Tensor:
    """Log density of the reverse process's prior at ``x`` (reference measure as in the module doc)."""
    g = diffusion.group
    sigma = diffusion.schedule.sigma_max
    rot = g.rotation_slice
    has_translation = (rot.stop - rot.start) < g.dim and g.point_dim == 3
    if diffusion.prior_name == "kernel":
        return diffusion.kernel.log_prob(x, g.identity(x.shape[:-2], dtype=x.dtype, device=x.device), sigma)
    log_haar = -math.log(8 * math.pi**2)  # SO(3) volume in the exponential-coordinate normalisation
    if g.point_dim != 3 or (rot.stop - rot.start) != 3:
        raise NotImplementedError(
            f"prior {diffusion.prior_name!r} log density is defined for 3-D rotation groups"
        )
    lp = torch.full(x.shape[:-2], log_haar, dtype=x.dtype, device=x.device)
    if not has_translation:
        return lp
    t = x[..., :3, 3]
    if diffusion.prior_name == "uniform":
        b = diffusion.prior_bound
        inside = (t.abs() <= b).all(-1)
        return torch.where(inside, lp - 3 * math.log(2 * b), torch.full_like(lp, -math.inf))
    st = sigma * diffusion.kernel.translation_scale
    return lp + (-0.5 * (t / st) ** 2 - math.log(st) - 0.5 * math.log(2 * math.pi)).sum(-1)


@torch.no_grad()
def log_likelihood(
    denoise_fn: DenoiseFn,
    diffusion: Diffusion,
    x: Tensor,
    cond: Any = None,
    *,
    num_steps: int | None = None,
    return_prior_point: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """``log p_{σ_min}(X)`` of poses ``x (B, N, n, n)`` under the score model, ``(B, N)``.

    Args:
        denoise_fn: the network, as for the samplers (``(x, sigma, cond) → output``).
        diffusion: the process it was trained with (kernel, schedule, parameterisation, prior).
        x: the poses to score, ``(B, N, n, n)`` (B conditions, N poses each).
        cond: the condition of the B inputs (as the samplers take it).
        num_steps: ODE steps, log-spaced from σ_min to σ_max (default 100).
        return_prior_point: also return ``X(σ_max)``, where the flow lands.
    """
    g = diffusion.group
    n = 100 if num_steps is None else int(num_steps)
    if n < 1:
        raise ValueError(f"log_likelihood: num_steps must be ≥ 1, got {num_steps}")
    if diffusion.objective == "flow":
        return _flow_log_likelihood(denoise_fn, diffusion, x, cond, n, return_prior_point)
    lo, hi = math.log(diffusion.schedule.sigma_min), math.log(diffusion.schedule.sigma_max)
    sig = torch.linspace(lo, hi, n + 1, dtype=torch.float64).exp().tolist()
    integral = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)
    v, div = _velocity_and_divergence(denoise_fn, diffusion, x, sig[0], cond)
    for s0, s1 in zip(sig[:-1], sig[1:], strict=True):
        # Heun in u = log σ (dX/du = X·(σ v)^): σ v stays O(1) near the data, where v ~ z/σ.
        h = math.log(s1 / s0)
        euler = g.rplus(x, h * s0 * v)
        v1, div1 = _velocity_and_divergence(denoise_fn, diffusion, euler, s1, cond)
        x = g.rplus(g.rplus(x, 0.5 * h * s0 * v), 0.5 * h * s1 * v1)
        integral = integral + 0.5 * h * (s0 * div + s1 * div1)
        v, div = _velocity_and_divergence(denoise_fn, diffusion, x, s1, cond)
    logp = prior_log_prob(diffusion, x) + integral
    return (logp, x) if return_prior_point else logp


def _flow_log_likelihood(
    denoise_fn: DenoiseFn, diffusion: Diffusion, x: Tensor, cond: Any, n: int, return_prior_point: bool
) -> Tensor | tuple[Tensor, Tensor]:
    """A flow model's ``log p₁(X)``: its ODE backwards from ``t = flow_t_max`` to 0 (module docstring)."""
    g = diffusion.group
    gap = 1.0 - min(diffusion.flow_t_max, 1.0 - 1e-6)  # 1 − t at the start
    ts = (1.0 - torch.logspace(math.log10(gap), 0.0, n + 1, dtype=torch.float64)).tolist()
    ts[-1] = 0.0
    integral = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)
    v, div = _velocity_and_divergence(denoise_fn, diffusion, x, ts[0], cond)
    for t0, t1 in zip(ts[:-1], ts[1:], strict=True):
        h = t1 - t0  # < 0: backwards in time
        euler = g.rplus(x, h * v)
        v1, div1 = _velocity_and_divergence(denoise_fn, diffusion, euler, t1, cond)
        x = g.rplus(g.rplus(x, 0.5 * h * v), 0.5 * h * v1)
        integral = integral + 0.5 * h * (div + div1)  # ∫_{t0}^{t1} div dt
        v, div = _velocity_and_divergence(denoise_fn, diffusion, x, t1, cond)
    # log p₁(X) = log p₀(X(0)) − ∫₀¹ div dt = log p₀(X(0)) + ∫₁⁰ div dt
    logp = prior_log_prob(diffusion, x) + integral
    return (logp, x) if return_prior_point else logp
