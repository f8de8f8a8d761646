"""Few-step students of a trained model: segment distillation of a score model's probability-flow ODE, and
rectification (reflow) of a flow model, on the group.

**Segment distillation** (``method=segment``, score models):

A student takes ``steps`` large steps of posediff's ``few_step`` sampler (order 1, no re-noising) on
the schedule's levels ``σ_0 > σ_1 > … > σ_{steps−1}`` (``schedule.timesteps(steps)``) and then 0::

    X_{j+1} = X_j · Exp((σ_{j+1} − σ_j) c ⊙ ẑ_S(X_j, σ_j))        (ẑ_S = −σ c ⊙ s_S, the student's)

Each student step is trained to land where the *teacher's* probability-flow ODE (``dX/dσ = X·(c ⊙
ẑ_T)^``, see :mod:`posediff.diffusion.ode`) lands from the same point: ``substeps`` Heun
(Crouch–Grossman) steps of the teacher, geometric in σ, over ``[σ_{j+1}, σ_j]`` (to σ_min and the
teacher's clean prediction for the last step). This is progressive distillation (Salimans & Ho,
2022: a student step matches two teacher steps, halving the steps per round) collapsed into one
round — every student step matches ``substeps`` teacher steps of its segment — on the group:
the target of the student's unit-noise output is, exactly,

    ẑ* = Log(X_j⁻¹ X*_{j+1}) / ((σ_{j+1} − σ_j) c)

so that ``ẑ_S = ẑ*`` puts the student's endpoint on the teacher's, and the loss is
``‖ẑ_S − ẑ*‖²`` (unit scale at every level). The points ``X_j`` are where the teacher's ODE is at
σ_j on its way from the prior (on-trajectory states, so the student is trained where it will be
sampled): a training batch draws ``num_hypotheses`` prior poses per input and runs the teacher
over the whole grid once; the student takes ``reuse`` updates on those trajectories.

The student starts as a copy of the teacher; only its denoiser is trained (the encoder is the
teacher's, frozen: the flow map is a function of the same image feature, and the encoder is run
once per batch for both). The result is a normal posediff checkpoint (the teacher's run config with
``module.sampler`` set to ``few_step`` at ``num_steps=steps`` and a ``distill`` record) that
``posediff eval`` / ``predict`` / ``export`` use unchanged.

**Rectification** (``method=reflow``, flow models trained with ``diffusion.objective=flow``; Liu et al.
2023, "Flow straight and fast", on the group): the teacher's ODE (``flow_heun``, ``teacher_steps``
steps) couples each prior draw ``X₀`` with the pose it carries it to, ``X₁ = Φ_T(X₀)``; the student (a
copy of the teacher, its denoiser trained) is re-fitted by the same flow objective on those pairs
(:meth:`~posediff.diffusion.Diffusion.interpolate` with the given ``x0``): ``X_t = X₀·Exp(t·u)``,
``u = Log(X₀⁻¹X₁)``, loss ``‖u_S(X_t, t) − u‖²``. The coupling no longer crosses itself, so the refitted
flow is straighter and its Euler steps land closer with fewer of them; it samples with ``flow_euler``
at ``steps`` steps. ``rounds=2`` rectifies the rectified flow once more (its own pairs).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import lightning as L
import torch
from torch import Tensor

from ..diffusion import Diffusion
from ..models import PoseDiffusionModule

#: the sampler of every reflow student (its steps are set from ``steps``)
REFLOW_SAMPLER: dict[str, Any] = {
    "_target_": "posediff.diffusion.FlowEulerSampler",
    "_partial_": True,
    "spacing": "uniform",
    "rotation_rate": 0.0,
}
#: ``posediff distill method=``: what each straightens
METHODS = {"segment": "dsm", "reflow": "flow"}

#: the sampler of every segment student (its steps are set from ``steps``)
STUDENT_SAMPLER: dict[str, Any] = {
    "_target_": "posediff.diffusion.FewStepSampler",
    "_partial_": True,
    "order": 1,
    "renoise": 0.0,
}


class DistillationError(ValueError):
    """A teacher or an option distillation cannot use (one-line message)."""


def student_grid(diffusion: Diffusion, steps: int) -> tuple[list[float], list[float]]:
    """``(σ_t, σ_p)`` of the student's ``steps`` steps (the ``few_step`` sampler's grid)."""
    levels = diffusion.schedule.timesteps(steps)
    sig = diffusion.schedule.sigma(levels, dtype=torch.float64).tolist()
    return sig, [*sig[1:], 0.0]


def _unit_noise(diffusion: Diffusion, out: Tensor, x: Tensor, sigma: Tensor) -> Tensor:
    """``ẑ = −σ c ⊙ s`` of a network output at noise ``sigma (B, N)``."""
    c = diffusion.kernel.scales(dtype=x.dtype, device=x.device)
    return -sigma.unsqueeze(-1) * c * diffusion.to_score(out, sigma)


@torch.no_grad()
def teacher_segments(
    teacher: PoseDiffusionModule,
    feature: Tensor,
    x: Tensor,
    sig_t: list[float],
    sig_p: list[float],
    substeps: int,
) -> list[Tensor]:
    """The teacher's ODE states at the student's grid points, from the prior draw ``x`` (``(B, N, n, n)``):
    ``steps + 1`` tensors, ``X_0 = x`` … ``X_steps`` (the teacher's clean end point)."""
    d, g = teacher.diffusion, teacher.group
    fn = teacher.denoise_fn()
    c2 = d.kernel.scales(dtype=x.dtype, device=x.device) ** 2

    def velocity(y: Tensor, sigma: float) -> Tensor:
        sig = torch.full(y.shape[:-2], sigma, dtype=y.dtype, device=y.device)
        return -sigma * c2 * d.to_score(fn(y, sig, feature), sig)

    states = [x]
    lo = d.schedule.sigma_min
    for a, b in zip(sig_t, sig_p, strict=True):
        end = b if b > 0 else lo
        if end < a:
            grid = torch.logspace(math.log10(a), math.log10(end), substeps + 1, dtype=torch.float64).tolist()
            for s0, s1 in zip(grid[:-1], grid[1:], strict=True):
                h = s1 - s0
                k1 = velocity(x, s0)
                k2 = velocity(g.rplus(x, h * k1), s1)
                x = g.rplus(g.rplus(x, 0.5 * h * k1), 0.5 * h * k2)
        if b == 0.0:  # the clean prediction from σ_min: the Euler step to 0
            x = g.rplus(x, -end * velocity(x, end))
        states.append(x)
    return states


class SegmentDistillation(L.LightningModule):
    """Trains ``student`` (a copy of ``teacher``) to take ``steps`` ``few_step`` steps that land where the
    teacher's ODE lands (module docstring).

    Args:
        teacher: the trained diffusion model (frozen).
        steps: the student's steps (= its network evaluations per sample).
        substeps: teacher Heun steps per student step (2 evaluations each).
        num_hypotheses: prior draws per training input.
        reuse: student updates per batch of teacher trajectories (the teacher's ODE costs
            ``2 · substeps`` evaluations per student step; reusing it amortises that).
        lr, lr_final: Adam on the student's denoiser, decayed exponentially to ``lr_final``.
    """

    def __init__(
        self,
        teacher: PoseDiffusionModule,
        *,
        steps: int,
        substeps: int = 4,
        num_hypotheses: int = 16,
        reuse: int = 4,
        lr: float = 1e-4,
        lr_final: float = 1e-5,
    ) -> None:
        super().__init__()
        self.student = copy.deepcopy(teacher).train()
        for p in self.student.parameters():
            p.requires_grad_(False)
        for p in self.student.denoiser.parameters():
            p.requires_grad_(True)
        self.teacher = teacher.eval()
        for p in self.teacher.parameters():
            p.requires_grad_(False)
        self.steps = int(steps)
        self.substeps = int(substeps)
        self.num_hypotheses = int(num_hypotheses)
        self.reuse = int(reuse)
        self.lr = float(lr)
        self.lr_final = float(lr_final)
        self._pool: tuple[Tensor, list[Tensor]] | None = None
        self._pool_uses = 0
        self.sig_t, self.sig_p = student_grid(teacher.diffusion, self.steps)
        self.loss_history: list[float] = []

    @torch.no_grad()
    def teacher_pool(
        self, cond: Any, generator: torch.Generator | None = None
    ) -> tuple[Tensor, list[Tensor]]:
        """``(feature, states)``: the teacher's feature of the inputs and its ODE states at the student's
        grid points for ``num_hypotheses`` prior draws per input (:func:`teacher_segments`)."""
        teacher, d = self.teacher, self.teacher.diffusion
        feature = teacher.encode(cond)
        x0 = d.prior(
            (int(feature.shape[0]), self.num_hypotheses),
            generator=generator,
            dtype=feature.dtype,
            device=feature.device,
        )
        return feature, teacher_segments(teacher, feature, x0, self.sig_t, self.sig_p, self.substeps)

    def student_loss(self, feature: Tensor, states: list[Tensor]) -> Tensor:
        """``mean ‖ẑ_S − ẑ*‖²`` over every student step of the teacher's trajectories ``states``."""
        d, g = self.student.diffusion, self.student.group
        x = torch.stack(states[:-1])  # (S, B, N, n, n): where each student step starts
        target = torch.stack(states[1:])
        c = d.kernel.scales(dtype=x.dtype, device=x.device)
        sig_t = torch.tensor(self.sig_t, dtype=x.dtype, device=x.device)
        h = torch.tensor(self.sig_p, dtype=x.dtype, device=x.device) - sig_t  # (S,)
        z_star = g.rminus(x, target) / (h.view(-1, 1, 1, 1) * c)  # Log(X_j⁻¹ X*_{j+1}) / (h c)
        S, B, N = x.shape[:3]
        flat = x.reshape(S * B, N, *x.shape[-2:])
        sigma = sig_t.view(S, 1, 1).expand(S, B, N).reshape(S * B, N)
        feat = feature.repeat(S, *([1] * (feature.ndim - 1)))
        out = self.student(flat, sigma, feat)
        z_student = _unit_noise(d, out, flat, sigma).reshape(S, B, N, -1)
        return (z_student - z_star).square().mean()

    def distillation_loss(self, cond: Any, generator: torch.Generator | None = None) -> Tensor:
        """The student's loss on fresh teacher trajectories of the inputs ``cond``."""
        return self.student_loss(*self.teacher_pool(cond, generator))

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        if self._pool is None or self._pool_uses >= self.reuse:  # the teacher's trajectories, reused
            self._pool, self._pool_uses = self.teacher_pool(batch[self.student.cond_key]), 0
        self._pool_uses += 1
        loss = self.student_loss(*self._pool)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite distillation loss {loss.item()} at step {self.global_step}")
        self.log("train/loss", loss, prog_bar=True, batch_size=int(batch["pose"].shape[0]))
        self.loss_history.append(float(loss.detach()))
        return loss

    def configure_optimizers(self) -> dict[str, Any]:
        params = [p for p in self.student.denoiser.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=self.lr)
        total = max(int(getattr(self.trainer, "max_steps", -1) or -1), 1)
        ratio = self.lr_final / self.lr

        def factor(step: int) -> float:
            return max(ratio ** (step / total), ratio)

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def student_config(self, teacher_config: dict[str, Any], record: dict[str, Any]) -> dict[str, Any]:
        """The teacher's run config with the student's sampler and a ``distill`` record."""
        config = copy.deepcopy(teacher_config)
        config["module"]["sampler"] = {**STUDENT_SAMPLER, "num_steps": self.steps}
        config["distill"] = record
        return config


class Reflow(SegmentDistillation):
    """Rectifies a flow model (module docstring): the student re-fitted by flow matching on the pairs
    ``(X₀, Φ_T(X₀))`` of the teacher's ODE.

    Args:
        teacher: the trained flow model (frozen).
        steps: the student's ``flow_euler`` steps.
        teacher_steps: ``flow_heun`` steps of the teacher's ODE (``2·teacher_steps − 1`` evaluations).
        num_hypotheses, reuse, lr, lr_final: as :class:`SegmentDistillation`.
    """

    def __init__(
        self,
        teacher: PoseDiffusionModule,
        *,
        steps: int,
        teacher_steps: int = 20,
        num_hypotheses: int = 16,
        reuse: int = 4,
        lr: float = 1e-4,
        lr_final: float = 1e-5,
    ) -> None:
        if teacher.diffusion.objective != "flow":
            raise DistillationError(
                "method=reflow straightens a flow model (diffusion.objective=flow); this teacher is a score "
                "model: use method=segment"
            )
        super().__init__(
            teacher, steps=1, num_hypotheses=num_hypotheses, reuse=reuse, lr=lr, lr_final=lr_final
        )
        from ..diffusion import FlowHeunSampler

        self.steps = int(steps)
        self.teacher_steps = int(teacher_steps)
        self.teacher_sampler = FlowHeunSampler(teacher.diffusion)
        self.sig_t, self.sig_p = [float(v) for v in self.teacher_sampler.sigma_grid(self.steps)[0]], []

    @torch.no_grad()
    def teacher_pool(
        self, cond: Any, generator: torch.Generator | None = None
    ) -> tuple[Tensor, list[Tensor]]:
        """``(feature, [X₀, X₁])``: prior draws and where the teacher's ODE carries them."""
        teacher, d = self.teacher, self.teacher.diffusion
        feature = teacher.encode(cond)
        x0 = d.prior(
            (int(feature.shape[0]), self.num_hypotheses), generator=generator, dtype=feature.dtype,
            device=feature.device,
        )  # fmt: skip
        fn = teacher.denoise_fn()
        x = x0
        t0, t1 = self.teacher_sampler.sigma_grid(self.teacher_steps)
        for a, b in zip(t0.tolist(), t1.tolist(), strict=True):
            x = self.teacher_sampler.step(fn, x, a, b, feature, None)
        return feature, [x0, x]

    def student_loss(self, feature: Tensor, states: list[Tensor]) -> Tensor:
        """The flow objective on the teacher's pairs: ``mean ‖u_S(X_t, t) − Log(X₀⁻¹X₁)‖²``."""
        x0, x1 = states
        batch = self.student.diffusion.interpolate(x1, x0=x0)
        out = self.student(batch.x_noisy, batch.sigma, feature)
        return self.student.diffusion.loss(out, batch)

    def student_config(self, teacher_config: dict[str, Any], record: dict[str, Any]) -> dict[str, Any]:
        config = copy.deepcopy(teacher_config)
        config["module"]["sampler"] = {**REFLOW_SAMPLER, "num_steps": self.steps}
        config["distill"] = record
        return config


def save_student(student: PoseDiffusionModule, config: dict[str, Any], path: Any) -> Any:
    """Write ``student`` as a posediff checkpoint (``state_dict`` + run config) atomically, as ``posediff
    fit`` writes its checkpoints (:func:`posediff.training.checkpoint_io.save_torch`: a temporary name in the same
    folder, fsynced, renamed; a full disk is a one-line :class:`~posediff.training.checkpoint_io.CheckpointWriteError`)."""
    from ..models.checkpoint import CONFIG_KEY
    from .checkpoint_io import save_torch

    student.config = config
    checkpoint = {
        "state_dict": student.state_dict(),
        CONFIG_KEY: config,
        "posediff_diffusion": student.diffusion.describe(),
        "hyper_parameters": dict(student.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    return save_torch(checkpoint, path)


__all__ = [
    "METHODS",
    "REFLOW_SAMPLER",
    "Reflow",
    "DistillationError",
    "SegmentDistillation",
    "STUDENT_SAMPLER",
    "save_student",
    "student_grid",
    "teacher_segments",
]
