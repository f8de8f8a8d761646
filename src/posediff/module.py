"""``PoseDiffusionModule``: the LightningModule that trains a score model and samples poses with it.

It wires an encoder (the condition → a feature vector; the identity for the toy, a ResNet for
images), a denoiser network (``posediff.nn.MLPDenoiser``), a ``Diffusion`` (kernel, schedule, score
target, output parameterisation, loss, prior) and a sampler factory. The encoder runs **once per
input**; its feature is broadcast to the ``num_noisy`` noisy poses of that input (paper: 16 images ×
256 noisy poses per step), and to the N hypotheses when sampling.

Batches are dicts with ``pose (B, n, n)`` and the condition under ``cond_key`` (default ``"cond"``).
The network sees ``Log(X̃)`` (the tangent vector of the noisy pose, paper §4.4; ``pose_input=
"tangent"``) or, as an option beyond the paper, the entries of the pose matrix (``pose_input=
"matrix"``: the 3×3 rotation, plus the translation column for 4×4 groups — smooth everywhere, no
re-wrapping of the rotation vector at θ = π), and the continuous noise-level index
``schedule.level(σ)`` (the authors feed the level index).
"""

from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from .diffusion import Diffusion, Sampler


class PoseDiffusionModule(L.LightningModule):
    """Score-based pose diffusion on a Lie group, trained with denoising score matching (paper Alg. 1).

    Args:
        diffusion: the forward process and objective.
        denoiser: ``net(tangent (B,N,dim), noise_level (B,N), feature (B,F)) → (B,N,dim)``.
        sampler: a factory ``sampler(diffusion) → Sampler`` (Hydra ``_partial_: true``).
        encoder: maps ``batch[cond_key]`` to the ``(B, F)`` feature (default: identity).
        num_noisy: noisy poses per input per step (paper: 256).
        lr, lr_final, decay_start: Adam at ``lr``, exponential decay to ``lr_final`` from the fraction
            ``decay_start`` of ``trainer.max_steps`` to the end (paper: 1e-4 → 1e-5 over the second half).
        weight_decay: > 0 uses AdamW (the authors' code: 1e-4).
        pose_input: what the denoiser sees of the noisy pose: ``"tangent"`` (``Log X̃``, the paper)
            or ``"matrix"`` (the top 3 rows of ``X̃``, flattened); see :meth:`pose_input_dim`.
    """

    POSE_INPUTS = ("tangent", "matrix")

    def __init__(
        self,
        diffusion: Diffusion,
        denoiser: nn.Module,
        sampler: Callable[[Diffusion], Sampler],
        *,
        encoder: nn.Module | None = None,
        cond_key: str = "cond",
        num_noisy: int = 256,
        lr: float = 1e-4,
        lr_final: float = 1e-5,
        decay_start: float = 0.5,
        weight_decay: float = 0.0,
        pose_input: str = "tangent",
    ) -> None:
        super().__init__()
        if pose_input not in self.POSE_INPUTS:
            raise ValueError(
                f"unknown pose_input {pose_input!r}; choose one of: {', '.join(self.POSE_INPUTS)}"
            )
        self.pose_input = pose_input
        self.diffusion = diffusion
        self.denoiser = denoiser
        self.encoder = encoder if encoder is not None else nn.Identity()
        self.sampler = sampler(diffusion) if not isinstance(sampler, Sampler) else sampler
        self.cond_key = cond_key
        self.num_noisy = int(num_noisy)
        self.lr = float(lr)
        self.lr_final = float(lr_final)
        self.decay_start = float(decay_start)
        self.weight_decay = float(weight_decay)
        #: the resolved run configuration, stored in checkpoints when set (by ``posediff fit``)
        self.config: dict[str, Any] | None = None
        #: the training loss of every step (floats), for run summaries
        self.loss_history: list[float] = []

    @property
    def group(self):  # noqa: ANN201 - LieGroup
        return self.diffusion.group

    # ------------------------------------------------------------------ the network
    def encode(self, cond: Any) -> Tensor:
        """The per-input feature, computed once per input."""
        return self.encoder(cond)

    @staticmethod
    def pose_input_dim(group: Any, pose_input: str) -> int:
        """Width of the denoiser's pose input: the tangent dimension, or 3·n for an n×n matrix."""
        if pose_input == "tangent":
            return int(group.dim)
        if pose_input == "matrix":
            return 3 * int(group.matrix_dim)
        raise ValueError(f"unknown pose_input {pose_input!r}; choose one of: tangent, matrix")

    def pose_features(self, x_noisy: Tensor) -> Tensor:
        """What the denoiser sees of ``x_noisy (..., n, n)``: ``(..., pose_input_dim)``."""
        if self.pose_input == "matrix":
            return x_noisy[..., :3, :].flatten(-2)
        return self.group.log(x_noisy)

    def forward(self, x_noisy: Tensor, sigma: Tensor, feature: Tensor) -> Tensor:
        """Raw network output at noisy poses ``x_noisy (B, N, n, n)`` with levels ``sigma (B, N)``."""
        level = self.diffusion.schedule.level(sigma)
        return self.denoiser(self.pose_features(x_noisy), level, feature)

    def denoise_fn(self) -> Callable[[Tensor, Tensor, Tensor], Tensor]:
        """The ``denoise_fn(x, sigma, feature)`` the samplers call."""
        return self.forward

    # ------------------------------------------------------------------ training
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        feature = self.encode(batch[self.cond_key])
        noisy = self.diffusion.perturb(batch["pose"], num_noisy=self.num_noisy)
        out = self(noisy.x_noisy, noisy.sigma, feature)
        loss = self.diffusion.loss(out, noisy)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite training loss {loss.item()} at step {self.global_step}")
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["pose"].shape[0])
        self.loss_history.append(float(loss.detach()))
        return loss

    @torch.no_grad()
    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """The training objective on held-out inputs (``val/loss``: what "best" checkpoints track)."""
        feature = self.encode(batch[self.cond_key])
        gen = torch.Generator(device=feature.device).manual_seed(1000 + batch_idx)
        noisy = self.diffusion.perturb(batch["pose"], num_noisy=self.num_noisy, generator=gen)
        loss = self.diffusion.loss(self(noisy.x_noisy, noisy.sigma, feature), noisy)
        self.log("val/loss", loss, prog_bar=True, batch_size=batch["pose"].shape[0])
        return loss

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.config is not None:
            checkpoint["posediff_config"] = self.config
            checkpoint["posediff_diffusion"] = self.diffusion.describe()

    def configure_optimizers(self) -> dict[str, Any]:
        params = [p for p in self.parameters() if p.requires_grad]
        if self.weight_decay > 0:
            opt: torch.optim.Optimizer = torch.optim.AdamW(params, lr=self.lr, weight_decay=self.weight_decay)
        else:
            opt = torch.optim.Adam(params, lr=self.lr)
        total = max(int(getattr(self.trainer, "max_steps", -1) or -1), 1)
        start = int(self.decay_start * total)
        ratio = self.lr_final / self.lr

        def factor(step: int) -> float:
            if step < start or total <= start:
                return 1.0
            return max(ratio ** ((step - start) / (total - start)), ratio)

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ sampling
    @torch.no_grad()
    def sample(
        self,
        cond: Any,
        num_samples: int,
        num_steps: int | None = None,
        *,
        sampler: Sampler | None = None,
        generator: torch.Generator | None = None,
        trajectory: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """``num_samples`` pose hypotheses per input, ``(B, N, n, n)`` (the encoder runs once per input)."""
        feature = self.encode(cond)
        s = sampler or self.sampler
        return s.sample(
            self.denoise_fn(),
            feature,
            num_samples,
            num_steps,
            generator,
            trajectory=trajectory,
            batch_size=int(feature.shape[0]),
            dtype=feature.dtype,
            device=feature.device,
        )
