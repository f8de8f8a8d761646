"""Reverse-process samplers on a Lie group.

A sampler is stateless: its constructor takes the ``Diffusion`` (group, kernel, schedule, output
parameterisation, prior) and options; ``sample`` runs the reverse process::

    poses = sampler.sample(denoise_fn, cond, num_samples=1000, num_steps=10, generator=g)

``denoise_fn(x, sigma, cond)`` is the network: ``x (B, N, n, n)`` noisy poses, ``sigma (B, N)`` their
noise level, ``cond`` the condition for the B inputs (any object the network understands, often a
``(B, C)`` tensor; the condition is *not* repeated N times — the network broadcasts it). It returns
the raw network output ``(B, N, dim)``; the sampler converts it with ``Diffusion.to_score``.

Every step moves from level σ_t to the next lower level σ_p (0 after the last level) with right
multiplications ``X ← X · Exp(·)``, so the result stays on the group exactly. Writing the score as
``s`` and the per-component σ as σ_c:

* ``random_walk`` — the paper's geodesic random walk (Eq. 7, Alg. 2):
  ``X ← X · Exp(ε s + √(2ε) n)``; step size ``ε = σ_t² − σ_p²`` (``step_size="reverse_diffusion"``)
  or annealed Langevin ``ε = step_scale · σ_t²`` repeated ``langevin_steps`` times per level
  (``step_size="langevin"``). ``noise="sde"`` uses ``√ε n`` (the reverse-SDE discretisation).
* ``ancestral`` — the authors' code: ``X̂₀ = X · Exp(σ_t² s)``, then
  ``X ← X̂₀ · Exp(c · ẑ) · Exp(ς n)`` with ``ẑ = −σ_t s``, ``ς = η (σ_p/σ_t) √(σ_t² − σ_p²)``,
  ``c = √(σ_p² − ς²)`` (η = 1: DDPM-like, η = 0: DDIM). ``offbyone_compat`` reproduces the code's
  σ_p = σ_{p−1}.
* ``few_step`` — posediff's deterministic few-step sampler: predict the clean pose
  ``X̂₀ = X · Exp(σ_t² s)`` — exact in one step when the network is the surrogate target of a single
  noise draw, because ``X̃ · Exp(−z) = X`` on any group — and re-noise along the same direction to
  σ_p: ``X ← X̂₀ · Exp(σ_p ẑ) = X · Exp(−(σ_t − σ_p) ẑ)`` (the Euler step of the probability-flow ODE
  ``dX/dσ = X · ẑ^`` in σ). ``order=2`` adds a Crouch–Grossman/Heun correction (two network calls
  per step); ``renoise`` ∈ [0, 1] mixes fresh noise into the re-noising direction.

Prior: ``Diffusion.prior`` (the kernel at σ_max; Haar-uniform rotation or the code's box as options).
"""

import math
from collections.abc import Callable
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from .._registry import Registered
from .process import Diffusion

DenoiseFn = Callable[[Tensor, Tensor, Any], Tensor]


class Sampler(Registered, family=True):
    """Base class: the prior draw, the level loop and the trajectory; subclasses implement ``step``."""

    family_label: ClassVar[str] = "sampler"
    name: ClassVar[str]
    #: the sampler claims to land on the modes of the exact score, with their weights, at 5 network
    #: evaluations (the ``five_nfe`` contract check holds it to that)
    few_nfe: ClassVar[bool] = False
    #: the training objective whose network this sampler reads (``Diffusion.objective``): ``"dsm"``
    #: samplers read a score, ``"flow"`` samplers (:mod:`posediff.diffusion.flow`) a velocity
    objective: ClassVar[str] = "dsm"

    def __init__(self, diffusion: Diffusion, *, num_steps: int | None = None) -> None:
        model = getattr(diffusion, "objective", "dsm")
        if model != type(self).objective:
            kind = {
                "dsm": "score models (diffusion.objective=dsm)",
                "flow": "flow models (diffusion.objective=flow)",
            }
            fits = sorted(n for n, c in Sampler.registry.items() if c.objective == model)
            raise ValueError(
                f"sampler {getattr(self, 'name', type(self).__name__)!r} samples {kind[type(self).objective]}, "
                f"this model is trained with diffusion.objective={model}; use sampler={' or sampler='.join(fits)}"
            )
        self.diffusion = diffusion
        if num_steps is not None:  # refused here, when built, not at the end of a training run
            levels = diffusion.schedule.num_levels
            if isinstance(num_steps, bool) or int(num_steps) != num_steps or not 1 <= num_steps <= levels:
                raise ValueError(
                    f"sampler.num_steps must be a whole number in [1, {levels}] (the schedule's levels), "
                    f"got {num_steps}"
                )
            num_steps = int(num_steps)
        self.num_steps = num_steps

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_steps={self.num_steps})"

    @property
    def group(self):  # noqa: ANN201 - LieGroup
        return self.diffusion.group

    def network_calls(self, num_steps: int) -> int:
        """How many times ``denoise_fn`` runs for ``num_steps`` steps."""
        return num_steps

    @torch.no_grad()
    def sample(
        self,
        denoise_fn: DenoiseFn,
        cond: Any,
        num_samples: int,
        num_steps: int | None = None,
        generator: torch.Generator | None = None,
        *,
        trajectory: bool = False,
        batch_size: int | None = None,
        dtype: torch.dtype | None = None,
        device: Any = None,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Draw ``num_samples`` poses per condition: ``(B, N, n, n)``.

        Args:
            denoise_fn: the network, ``(x (B,N,n,n), sigma (B,N), cond) → (B,N,dim)``.
            cond: the condition of B inputs: a tensor whose first dimension is B, or None (B = 1
                unless ``batch_size`` says otherwise).
            num_samples: N hypotheses per input.
            num_steps: how many levels to visit (default: the sampler's, else every level).
            generator: the random source (the prior draw and every noise draw).
            trajectory: also return every intermediate pose, ``(num_steps + 1, B, N, n, n)``.
        """
        if batch_size is None:
            batch_size = int(cond.shape[0]) if isinstance(cond, Tensor) else 1
        if isinstance(cond, Tensor):
            dtype = dtype or (cond.dtype if cond.is_floating_point() else None)
            device = device or cond.device
        dtype = dtype or torch.get_default_dtype()
        steps = num_steps if num_steps is not None else self.num_steps
        sig_t, sig_p = self.sigma_grid(steps)
        x = self.diffusion.prior(
            (batch_size, int(num_samples)), generator=generator, dtype=dtype, device=device
        )
        path = [x] if trajectory else None
        for j in range(len(sig_t)):
            x = self.step(denoise_fn, x, float(sig_t[j]), float(sig_p[j]), cond, generator)
            if path is not None:
                path.append(x)
        if path is not None:
            return x, torch.stack(path)
        return x

    def sigma_grid(self, num_steps: int | None = None) -> tuple[Tensor, Tensor]:
        """The noise levels of each step, ``(σ_t, σ_p)`` float64 ``(num_steps,)`` each: step ``j`` moves
        from ``σ_t[j]`` to ``σ_p[j]`` (0 after the last). Default: the schedule's ``timesteps``."""
        levels = self.diffusion.schedule.timesteps(num_steps)
        sig_t = self.diffusion.schedule.sigma(levels, dtype=torch.float64)
        return sig_t, self._next_sigmas(levels, sig_t)

    def _next_sigmas(self, levels: Tensor, sig_t: Tensor) -> Tensor:
        return torch.cat([sig_t[1:], sig_t.new_zeros(1)])

    def steps_for_nfe(self, nfe: int) -> int:
        """The most steps whose network evaluations fit in ``nfe`` (at least 1): how the few-step
        tables compare samplers at equal cost."""
        levels = self.diffusion.schedule.num_levels
        best = 1
        for n in range(1, levels + 1):
            if self.network_calls(n) <= nfe:
                best = n
        return best

    # ------------------------------------------------------------------ helpers for steps
    def score(self, denoise_fn: DenoiseFn, x: Tensor, sigma: float, cond: Any) -> Tensor:
        """The score at ``x`` (network output converted by the diffusion's parameterisation)."""
        sig = torch.full(x.shape[:-2], sigma, dtype=x.dtype, device=x.device)
        out = denoise_fn(x, sig, cond)
        if out.shape != (*x.shape[:-2], self.group.dim):
            raise ValueError(
                f"denoise_fn returned {tuple(out.shape)}; expected {(*x.shape[:-2], self.group.dim)}"
            )
        return self.diffusion.to_score(out, sig)

    def sigma_c(self, sigma: float, like: Tensor) -> Tensor:
        """Per-component σ, ``(dim,)``."""
        return self.diffusion.kernel.scales(dtype=like.dtype, device=like.device) * sigma

    def noise(self, x: Tensor, generator: torch.Generator | None) -> Tensor:
        return torch.randn(
            (*x.shape[:-2], self.group.dim), generator=generator, dtype=x.dtype, device=x.device
        )

    def step(
        self,
        denoise_fn: DenoiseFn,
        x: Tensor,
        sigma_t: float,
        sigma_p: float,
        cond: Any,
        generator: torch.Generator | None,
    ) -> Tensor:
        raise NotImplementedError


class GeodesicRandomWalk(Sampler, name="random_walk"):
    """The paper's geodesic random walk, ``X ← X · Exp(ε s + √(2ε) n)`` (Eq. 7, Alg. 2).

    Args:
        step_size: ``"reverse_diffusion"`` (ε = σ_t² − σ_p²) or ``"langevin"`` (annealed Langevin,
            ε = ``step_scale`` · σ_t², ``langevin_steps`` steps per level).
        noise: ``"langevin"`` (√(2ε), Eq. 7 as written) or ``"sde"`` (√ε, the reverse-SDE step).
        final_denoise: end with the noise-free step ``X · Exp(σ_0² s)`` from the lowest level.
    """

    def __init__(
        self,
        diffusion: Diffusion,
        *,
        num_steps: int | None = None,
        step_size: Literal["reverse_diffusion", "langevin"] = "reverse_diffusion",
        noise: Literal["langevin", "sde"] = "langevin",
        step_scale: float = 0.1,
        langevin_steps: int = 1,
        final_denoise: bool = True,
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps)
        if step_size not in ("reverse_diffusion", "langevin"):
            raise ValueError(
                f"random_walk: unknown step_size {step_size!r}; options: reverse_diffusion, langevin"
            )
        if noise not in ("langevin", "sde"):
            raise ValueError(f"random_walk: unknown noise {noise!r}; options: langevin, sde")
        self.step_size = step_size
        self.noise_kind = noise
        self.step_scale = float(step_scale)
        self.langevin_steps = int(langevin_steps)
        self.final_denoise = bool(final_denoise)

    def network_calls(self, num_steps: int) -> int:
        per = self.langevin_steps if self.step_size == "langevin" else 1
        last = 1 if self.final_denoise else per
        return (num_steps - 1) * per + last

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        g = self.group
        if sigma_p == 0.0 and self.final_denoise:
            s = self.score(denoise_fn, x, sigma_t, cond)
            return g.rplus(x, self.sigma_c(sigma_t, x) ** 2 * s)
        factor = 2.0 if self.noise_kind == "langevin" else 1.0
        if self.step_size == "reverse_diffusion":
            eps = self.sigma_c(sigma_t, x) ** 2 - self.sigma_c(sigma_p, x) ** 2
            s = self.score(denoise_fn, x, sigma_t, cond)
            return g.rplus(x, eps * s + (factor * eps).sqrt() * self.noise(x, generator))
        eps = self.step_scale * self.sigma_c(sigma_t, x) ** 2
        for _ in range(self.langevin_steps):
            s = self.score(denoise_fn, x, sigma_t, cond)
            x = g.rplus(x, eps * s + (factor * eps).sqrt() * self.noise(x, generator))
        return x


class AncestralSampler(Sampler, name="ancestral"):
    """The authors' ancestral step: predict ``X̂₀``, re-noise to σ_p with fresh noise (η).

    Args:
        eta: 1 — the code's default (stochastic); 0 — DDIM (deterministic).
        offbyone_compat: target σ_{p−1} instead of σ_p at each step, as the authors' code does
            (each intermediate state is then one level less noisy than the network is told).
    """

    def __init__(
        self,
        diffusion: Diffusion,
        *,
        num_steps: int | None = None,
        eta: float = 1.0,
        offbyone_compat: bool = False,
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps)
        if not 0.0 <= eta <= 1.0:
            raise ValueError(f"ancestral: eta must be in [0, 1], got {eta}")
        self.eta = float(eta)
        self.offbyone_compat = bool(offbyone_compat)

    def _next_sigmas(self, levels: Tensor, sig_t: Tensor) -> Tensor:
        if not self.offbyone_compat:
            return super()._next_sigmas(levels, sig_t)
        nxt = torch.cat([levels[1:], levels.new_zeros(1)]) - 1
        table = self.diffusion.schedule.sigmas
        out = torch.where(nxt >= 0, table[nxt.clamp_min(0)], torch.zeros_like(table[:1]).expand_as(nxt))
        out[-1] = 0.0
        return out

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        g = self.group
        s = self.score(denoise_fn, x, sigma_t, cond)
        st, sp = self.sigma_c(sigma_t, x), self.sigma_c(sigma_p, x)
        zhat = -st * s  # unit noise estimate
        x0 = g.rplus(x, -st * zhat)  # X · Exp(σ_t² s)
        if sigma_p == 0.0:
            return x0
        spread = self.eta * (sp / st) * (st**2 - sp**2).clamp_min(0).sqrt()
        c = (sp**2 - spread**2).clamp_min(0).sqrt()
        x = g.rplus(x0, c * zhat)
        if self.eta > 0:
            x = g.rplus(x, spread * self.noise(x, generator))
        return x


class FewStepSampler(Sampler, name="few_step"):
    """Deterministic predict-clean-then-re-noise on the group (posediff's few-step sampler).

    Args:
        order: 1 — one network call per step (``X ← X · Exp(−(σ_t − σ_p) ẑ_t)``); 2 — Heun-type
            Crouch–Grossman correction ``X ← X · Exp(½h ẑ_t) · Exp(½h ẑ')`` with ``h = σ_p − σ_t`` and
            ``ẑ'`` evaluated at the Euler prediction (two calls per step except the last).
        renoise: fraction η of fresh noise in the re-noising direction, ``√(1−η²) ẑ + η n``
            (0: deterministic).
    """

    few_nfe: ClassVar[bool] = True

    def __init__(
        self, diffusion: Diffusion, *, num_steps: int | None = None, order: int = 1, renoise: float = 0.0
    ) -> None:
        super().__init__(diffusion, num_steps=num_steps)
        if order not in (1, 2):
            raise ValueError(f"few_step: order must be 1 or 2, got {order}")
        if not 0.0 <= renoise <= 1.0:
            raise ValueError(f"few_step: renoise must be in [0, 1], got {renoise}")
        if order == 2 and renoise > 0.0:
            raise ValueError("few_step: order=2 (the Heun correction of the ODE) needs renoise=0")
        self.order = int(order)
        self.renoise = float(renoise)

    def network_calls(self, num_steps: int) -> int:
        return num_steps if self.order == 1 else 2 * num_steps - 1

    def unit_noise(self, denoise_fn: DenoiseFn, x: Tensor, sigma: float, cond: Any) -> Tensor:
        """``ẑ = −σ_c ⊙ s``: the network's estimate of the unit noise that produced ``x``."""
        return -self.sigma_c(sigma, x) * self.score(denoise_fn, x, sigma, cond)

    def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
        g = self.group
        st, sp = self.sigma_c(sigma_t, x), self.sigma_c(sigma_p, x)
        zhat = self.unit_noise(denoise_fn, x, sigma_t, cond)
        if sigma_p == 0.0:
            return g.rplus(x, -st * zhat)  # the clean prediction
        if self.renoise > 0.0:
            x0 = g.rplus(x, -st * zhat)
            direction = math.sqrt(1.0 - self.renoise**2) * zhat + self.renoise * self.noise(x, generator)
            return g.rplus(x0, sp * direction)
        h = sp - st
        euler = g.rplus(x, h * zhat)
        if self.order == 1:
            return euler
        zhat2 = self.unit_noise(denoise_fn, euler, sigma_p, cond)
        return g.rplus(g.rplus(x, 0.5 * h * zhat), 0.5 * h * zhat2)
