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
    ) -> None:
        self.kernel = kernel
        self.schedule = schedule
        self.score_target = ScoreTarget.lookup(score)()
        _choice("output", output, ("score", "noise"))
        _choice("loss", loss, ("tangent_l2", "chordal"))
        _choice("weighting", weighting, ("sigma2", "none"))
        _choice("prior", prior, ("kernel", "haar", "uniform"))
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
            f"output={self.output!r}, loss={self.loss_name!r}, prior={self.prior_name!r})"
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
        ``levels`` is given.
        """
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
        if self.loss_name == "chordal":
            g = self.group
            diff = g.exp(output) - g.exp(batch.target.to(output.dtype))
            return diff.square().sum((-2, -1)).mean()
        w = torch.full((self.group.dim,), self.translation_weight, dtype=output.dtype, device=output.device)
        w[self.group.rotation_slice] = self.rotation_weight
        err = (output - batch.target.to(output.dtype)).square() * w
        if self.weighting == "none":
            err = err / self.kernel.component_sigma(batch.sigma, output).square()
        return err.sum(-1).mean()

    def loss_parts(self, output: Tensor, batch: NoisyBatch) -> dict[str, Tensor]:
        """The tangent-L2 loss split into its ``rotation`` and (groups with one) ``translation``
        components, unweighted by ``rotation_weight`` / ``translation_weight`` — a diagnostic (held-out
        rotation loss, per-part gradients), whatever ``loss`` trains."""
        err = (output - batch.target.to(output.dtype)).square()
        if self.weighting == "none":
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
        }


def _choice(what: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ValueError(f"Diffusion: unknown {what} {value!r}; options: {', '.join(options)}")
