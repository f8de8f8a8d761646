"""``Diffusion``: the forward process, the training target and loss, and the prior, in one object.

It bundles the choices that must agree between training and sampling:

* the **kernel** (``ConcentratedGaussian`` or ``IGSO3``) and its group;
* the **schedule** of noise levels;
* the **score target** (``surrogate`` −z/σ², paper Eq. 12; ``closed_form``, Eq. 5; ``autograd``,
  Eq. 18) — see ``posediff.diffusion.score``;
* what the **network outputs** (``output``):

  - ``"score"`` — the σ-scaled score ``σ_c ⊙ s`` (paper's parameterisation; for the surrogate
    this is ``−z/σ``);
  - ``"noise"`` — the unit noise ``−σ_c ⊙ s`` (the authors' code, ε-prediction; for the surrogate
    ``z/σ``). ``to_score`` converts either back to a score for the sampler;

* the **loss**:

  - ``"tangent_l2"`` — ``‖w ⊙ (output − target)‖²`` averaged over samples: denoising score matching
    (paper Eq. 6) with the weighting ``λ(σ) = σ²`` (NCSN's choice, which keeps every level's loss
    O(1)); ``weighting="none"`` gives the literal unweighted Eq. 6, numerically poor with
    σ_min = 1e-4 (its targets are O(1/σ));
  - ``"chordal"`` — ``‖Exp(output) − Exp(target)‖²_F`` on the group's matrices (the authors'
    code; with the surrogate and ``output="noise"`` it compares ``Exp(ẑ)`` with ``Exp(z/σ)``). It is
    invariant to 2π re-wrapping of the rotation part and weights rotation about twice as much
    as translation for small errors;

* the **objective** (``objective``): ``"dsm"`` — denoising score matching, everything above (the
  paper); ``"flow"`` — flow matching on the group (beyond the paper; Lipman et al. 2023 in R^n,
  FrameFlow / FoldFlow on SE(3)): the geodesic interpolant from a prior pose ``X₀`` to the data pose
  ``X₁``, ``X_t = X₀·Exp(t·Log(X₀⁻¹X₁))`` (on R³×SO(3) per part, on SE(3) the screw — each group's own
  Exp), and the network regresses the body velocity ``dX_t/dt = X_t·u^`` with the conditional target
  ``u = Log(X_t⁻¹X₁)/(1−t)``, constant along the geodesic and equal to ``Log(X₀⁻¹X₁)`` (computed so:
  no division near t = 1). ``X₀`` is Haar rotation × Gaussian translation of std σ_max ·
  ``translation_scale`` (the ``"haar"`` prior). Time reaches the network as a noise level: ``t`` ↦ the
  σ whose continuous level is ``(1−t)(L−1)`` (``flow_sigma``), so t = 0 is the top level (the prior)
  and t = 1 the bottom (the data), and the denoiser, anchor, fold and export are unchanged. Its
  samplers are ``flow_euler`` and ``flow_heun`` (:mod:`posediff.diffusion.flow`). ``score``,
  ``output``, ``loss`` and ``weighting`` are the DSM objective's and are not used by it;

* the **prior** of the reverse process (``prior``): ``"kernel"`` — the kernel at σ_max around the
  identity (the paper: "a Gaussian distribution on SE(3)"); ``"haar"`` — Haar-uniform rotation
  with the kernel's σ_max translation; ``"uniform"`` — Haar rotation × U[−b, b]³ translation (the
  authors' code, ``prior_bound = 1``).
"""

from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from ..lie import LieGroup
from .kernels import NoiseKernel
from .schedules import NoiseSchedule
from .score import ScoreTarget

Output = Literal["score", "noise"]
Objective = Literal["dsm", "flow"]
OBJECTIVES = ("dsm", "flow")
Loss = Literal["tangent_l2", "chordal"]
Prior = Literal["kernel", "haar", "uniform"]


@dataclass(frozen=True)
class NoisyBatch:
    """One training draw: ``x_noisy = x0 · Exp(z)`` at noise level ``sigma`` and the network target."""

    x_noisy: Tensor  # (*b, n, n)
    z: Tensor  # (*b, dim) principal tangent of the perturbation
    sigma: Tensor  # (*b,)
    level: Tensor  # (*b,) long, index into the schedule
    target: Tensor  # (*b, dim) what the network should output


class Diffusion:
    """Forward process + training objective + prior for score-based diffusion on a Lie group.

    Args:
        kernel: the perturbation kernel (carries the group).
        schedule: the noise levels.
        score: score-target name (``surrogate``, ``closed_form``, ``autograd``).
        output: ``"score"`` (σ-scaled score) or ``"noise"`` (unit noise, the authors' code).
        loss: ``"tangent_l2"`` (paper Eq. 6) or ``"chordal"`` (the authors' code).
        weighting: ``"sigma2"`` (default, λ(σ) = σ²) or ``"none"`` (literal Eq. 6); tangent_l2 only.
        rotation_weight, translation_weight: per-component loss weights (tangent_l2).
        prior: ``"kernel"``, ``"haar"`` or ``"uniform"``; ``prior_bound`` is the box of ``"uniform"``.
            The flow objective always starts from ``"haar"``.
        objective: ``"dsm"`` (denoising score matching, the paper) or ``"flow"`` (flow matching on the
            group, module docstring).
        flow_t_max: the largest training time of the flow objective (t ~ U[0, flow_t_max]); the
            network's time input stays off the exact endpoint t = 1, where ``X_t = X₁`` and the
            conditional target carries no information about the prior.
    """

    def __init__(
        self,
        kernel: NoiseKernel,
        schedule: NoiseSchedule,
        *,
        score: str = "surrogate",
        output: Output = "score",
        loss: Loss = "tangent_l2",
        weighting: Literal["sigma2", "none"] = "sigma2",
        rotation_weight: float = 1.0,
        translation_weight: float = 1.0,
        prior: Prior = "kernel",
        prior_bound: float = 1.0,
        objective: Objective = "dsm",
        flow_t_max: float = 0.999,
    ) -> None:
        self.kernel = kernel
        self.schedule = schedule
        self.score_target = ScoreTarget.lookup(score)()
        _choice("output", output, ("score", "noise"))
        _choice("loss", loss, ("tangent_l2", "chordal"))
        _choice("weighting", weighting, ("sigma2", "none"))
        _choice("prior", prior, ("kernel", "haar", "uniform"))
        _choice("objective", objective, OBJECTIVES)
        if not 0.0 < float(flow_t_max) <= 1.0:
            raise ValueError(f"Diffusion: flow_t_max must be in (0, 1], got {flow_t_max}")
        self.objective = objective
        self.flow_t_max = float(flow_t_max)
        if objective == "flow":
            prior = "haar"
        if loss == "chordal" and weighting != "sigma2":
            raise ValueError("Diffusion: weighting='none' applies to the tangent_l2 loss only")
        self.output = output
        self.loss_name = loss
        self.weighting = weighting
        self.rotation_weight = float(rotation_weight)
        self.translation_weight = float(translation_weight)
        self.prior_name = prior
        self.prior_bound = float(prior_bound)

    def __repr__(self) -> str:
        return (
            f"Diffusion({self.kernel!r}, {self.schedule!r}, score={self.score_target.name!r}, "
            f"output={self.output!r}, loss={self.loss_name!r}, prior={self.prior_name!r}"
            + (", objective='flow')" if self.objective == "flow" else ")")
        )

    @property
    def group(self) -> LieGroup:
        return self.kernel.group

    # ------------------------------------------------------------------ training
    def perturb(
        self,
        x0: Tensor,
        *,
        num_noisy: int | None = None,
        levels: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> NoisyBatch:
        """Draw noisy poses around clean poses ``x0 (*b, n, n)`` (paper Alg. 1).

        With ``num_noisy = K`` every clean pose gets K independent noisy copies, ``(*b, K, n, n)``
        (the paper uses 256 per image). Each copy draws its own level ``i ~ U{0..L−1}`` unless
        ``levels`` is given. With the flow objective see :meth:`interpolate`.
        """
        if self.objective == "flow":
            return self.interpolate(x0, num_noisy=num_noisy, generator=generator)
        if num_noisy is not None:
            x0 = x0.unsqueeze(-3).expand(*x0.shape[:-2], int(num_noisy), *x0.shape[-2:])
        batch = tuple(x0.shape[:-2])
        if levels is None:
            levels = self.schedule.sample_levels(batch, generator=generator, device=x0.device)
        levels = torch.broadcast_to(levels, batch)
        sigma = self.schedule.sigma(levels, dtype=x0.dtype)
        x_noisy, z = self.kernel.sample(x0, sigma, generator=generator)
        score = self.score_target(self.kernel, z, sigma)
        return NoisyBatch(
            x_noisy=x_noisy, z=z, sigma=sigma, level=levels, target=self.from_score(score, sigma)
        )

    def interpolate(
        self,
        x1: Tensor,
        *,
        num_noisy: int | None = None,
        t: Tensor | None = None,
        x0: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> NoisyBatch:
        """The flow objective's training draw: ``X_t = X₀·Exp(t·u)``, ``u = Log(X₀⁻¹X₁)`` between a
        prior pose ``X₀`` and the data pose ``x1 (*b, n, n)`` (``num_noisy`` copies each, as
        :meth:`perturb`). ``t ~ U[0, flow_t_max]`` unless given; ``x0`` (a prior draw per copy) is
        drawn unless given — rectification hands in the pairs it made. ``sigma`` is the network's time
        input (:meth:`flow_sigma`), ``z`` and ``target`` the body velocity ``u``.
        """
        g = self.group
        if num_noisy is not None:
            x1 = x1.unsqueeze(-3).expand(*x1.shape[:-2], int(num_noisy), *x1.shape[-2:])
        batch = tuple(x1.shape[:-2])
        if t is None:
            t = torch.rand(batch, generator=generator, dtype=x1.dtype, device=x1.device) * self.flow_t_max
        t = torch.broadcast_to(t.to(x1.dtype), batch)
        if x0 is None:
            x0 = self.prior(batch, generator=generator, dtype=x1.dtype, device=x1.device)
        u = g.rminus(x0, x1)  # Log(X₀⁻¹X₁) = Log(X_t⁻¹X₁)/(1−t) along the geodesic
        xt = g.rplus(x0, t.unsqueeze(-1) * u)
        sigma = self.flow_sigma(t)
        levels = self.schedule.level(sigma).round().long()
        return NoisyBatch(x_noisy=xt, z=u, sigma=sigma, level=levels, target=u)

    def flow_sigma(self, t: Tensor | float) -> Tensor:
        """The noise level that stands for flow time ``t``: the σ whose continuous level
        (``schedule.level``) is ``(1−t)(L−1)`` — t = 0 the top level, t = 1 the bottom."""
        t = torch.as_tensor(t, dtype=torch.float64) if not isinstance(t, Tensor) else t
        log_table = self.schedule.sigmas.log().to(device=t.device, dtype=torch.float64)
        pos = (1.0 - t.to(torch.float64)).clamp(0.0, 1.0) * (self.schedule.num_levels - 1)
        lo = pos.floor().long().clamp(0, self.schedule.num_levels - 1)
        hi = (lo + 1).clamp(max=self.schedule.num_levels - 1)
        frac = pos - lo.to(torch.float64)
        out = (log_table[lo] * (1 - frac) + log_table[hi] * frac).exp()
        return out.to(t.dtype if t.is_floating_point() else torch.get_default_dtype())

    def from_score(self, score: Tensor, sigma: Tensor | float) -> Tensor:
        """The network output that represents ``score`` at level σ (inverse of ``to_score``)."""
        sig = self.kernel.component_sigma(sigma, score)
        return sig * score if self.output == "score" else -sig * score

    def to_score(self, output: Tensor, sigma: Tensor | float) -> Tensor:
        """The score that a network ``output`` stands for at level σ (what samplers consume)."""
        sig = self.kernel.component_sigma(sigma, output)
        return output / sig if self.output == "score" else -output / sig

    def loss(self, output: Tensor, batch: NoisyBatch) -> Tensor:
        """The mean training loss of ``output (*b, dim)`` against ``batch.target``."""
        if output.shape != batch.target.shape:
            raise ValueError(
                f"Diffusion.loss: output {tuple(output.shape)} vs target {tuple(batch.target.shape)}"
            )
        if self.loss_name == "chordal" and self.objective == "dsm":
            g = self.group
            diff = g.exp(output) - g.exp(batch.target.to(output.dtype))
            return diff.square().sum((-2, -1)).mean()
        w = torch.full((self.group.dim,), self.translation_weight, dtype=output.dtype, device=output.device)
        w[self.group.rotation_slice] = self.rotation_weight
        err = (output - batch.target.to(output.dtype)).square() * w
        if self.weighting == "none" and self.objective == "dsm":
            err = err / self.kernel.component_sigma(batch.sigma, output).square()
        return err.sum(-1).mean()

    def loss_parts(self, output: Tensor, batch: NoisyBatch) -> dict[str, Tensor]:
        """The tangent-L2 loss split into its ``rotation`` and (groups with one) ``translation``
        components, unweighted by ``rotation_weight`` / ``translation_weight`` — a diagnostic (held-out
        rotation loss, per-part gradients), whatever ``loss`` trains."""
        err = (output - batch.target.to(output.dtype)).square()
        if self.weighting == "none" and self.objective == "dsm":
            err = err / self.kernel.component_sigma(batch.sigma, output).square()
        rot = self.group.rotation_slice
        parts = {"rotation": err[..., rot].sum(-1).mean()}
        if (rot.stop - rot.start) < self.group.dim:
            keep = torch.ones(self.group.dim, dtype=torch.bool, device=err.device)
            keep[rot] = False
            parts["translation"] = err[..., keep].sum(-1).mean()
        return parts

    # ------------------------------------------------------------------ sampling
    def prior(
        self,
        batch_shape: tuple[int, ...],
        *,
        generator: torch.Generator | None = None,
        dtype: torch.dtype | None = None,
        device: Any = None,
    ) -> Tensor:
        """Initial samples of the reverse process, ``(*batch_shape, n, n)``."""
        g = self.group
        dtype = dtype or torch.get_default_dtype()
        shape = tuple(batch_shape)
        if self.prior_name == "uniform":
            return g.sample_uniform(
                shape, generator=generator, device=device, dtype=dtype, bound=self.prior_bound
            )
        if self.objective == "flow":
            return self._flow_prior(shape, generator=generator, dtype=dtype, device=device)
        sigma = torch.full(shape, self.schedule.sigma_max, dtype=dtype, device=device)
        z = self.kernel.sample_tangent(sigma, generator=generator)
        x = g.exp(z)
        if self.prior_name == "haar":
            rot = g.rotation_slice
            has_translation = (rot.stop - rot.start) < g.dim
            haar = g.sample_uniform(shape, generator=generator, device=device, dtype=dtype)
            if has_translation:
                k = g.matrix_dim - 1
                x = x.clone()
                x[..., :k, :k] = haar[..., :k, :k]
            else:
                x = haar
        return x

    def _flow_prior(
        self, shape: tuple[int, ...], *, generator: torch.Generator | None, dtype: torch.dtype, device: Any
    ) -> Tensor:
        """Haar rotation × N(0, (σ_max · translation_scale)² I) translation: the density
        ``likelihood.prior_log_prob`` gives for the ``"haar"`` prior, exactly, on every group."""
        g = self.group
        x = g.sample_uniform(shape, generator=generator, device=device, dtype=dtype)
        rot = g.rotation_slice
        if (rot.stop - rot.start) < g.dim:
            k = g.matrix_dim - 1
            std = self.schedule.sigma_max * self.kernel.translation_scale
            x = x.clone()
            x[..., :k, k] = std * torch.randn((*shape, k), generator=generator, dtype=dtype, device=device)
        return x

    def describe(self) -> dict[str, Any]:
        """The configuration as plain values (stored with checkpoints and results)."""
        return {
            "group": self.group.name,
            "kernel": self.kernel.name,
            "schedule": self.schedule.name,
            "num_levels": self.schedule.num_levels,
            "sigma_min": self.schedule.sigma_min,
            "sigma_max": self.schedule.sigma_max,
            "score": self.score_target.name,
            "output": self.output,
            "loss": self.loss_name,
            "prior": self.prior_name,
            "objective": self.objective,
        }


def _choice(what: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ValueError(f"Diffusion: unknown {what} {value!r}; options: {', '.join(options)}")
