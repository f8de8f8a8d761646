"""``PoseRegressionModule``: the paper's two pose-regression baselines (Table 2, "Regression" and
"Iterative regression"), trained with a symmetry-aware loss and scored like the diffusion models.

* **Regression** (``iterations=0``): the encoder's pose head (:class:`~posediff.nn.PoseEncoder`:
  6-D rotation by Gram–Schmidt + translation; optionally locate-then-crop) regresses one pose.
* **Iterative regression** (``iterations=K``): that estimate refined K times,
  ``X_{k+1} = X_k · Exp(f(Log X_k, k, feature))``, each step conditioned on the current estimate and
  the image feature; ``f`` is the denoiser network (``posediff.nn.MLPDenoiser``) with the step index
  in place of the noise level. Every iterate is supervised (the mean of the K + 1 losses); the
  estimate entering a step is detached, as in iterative error feedback.

The loss is the minimum over the object's equivalent poses (SYMSOL's exact groups, cone and cylinder
in closed form, :func:`~posediff.symmetry.symmetric_chordal_sq`; BOP objects by their ``models_info``
symmetries, which the BOP data module puts in every sample): ``min_S ‖R̂ − R·S‖²_F`` plus
``translation_weight · ‖t̂ − t‖²``. The paper's regression baselines use symmetry labels; the
diffusion models do not.

For evaluation a regression model's "hypotheses" are its one estimate, repeated ``num_samples``
times, so ``posediff eval`` / ``fit`` report the same table (spread = the estimate's error; coverage
shows what one estimate covers). ``num_steps`` and samplers do not apply and are ignored.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from ..nn.pose_encoder import Encoding
from .base import PoseModule
from .losses import symmetric_rotation_loss

__all__ = ["PoseRegressionModule"]


class PoseRegressionModule(PoseModule):
    """Symmetry-aware pose regression (module docstring), a sibling of
    :class:`~posediff.models.PoseDiffusionModule`. Takes :class:`~posediff.models.base.PoseModule`'s
    arguments (the diffusion object only names the group; no denoising is trained) and:

    Args:
        iterations: refinement steps K (0: direct regression).
        translation_weight: weight of the translation's squared error.
        denoiser: the refinement network (``iterations > 0``; ``None`` for direct regression).
        sampler: kept so that one ``module`` config serves both kinds; a regression does not sample.
        num_noisy, symmetry_fold, grad_probe_every, anchor, aux_weight: the diffusion module's
            options, accepted so that ``module._target_=posediff.models.PoseRegressionModule`` turns
            any diffusion experiment into its regression baseline; they do not apply and are ignored.
    """

    def __init__(
        self,
        diffusion: Any,
        denoiser: nn.Module | None = None,
        sampler: Any = None,
        *,
        iterations: int = 0,
        translation_weight: float = 1.0,
        num_noisy: int | None = None,
        symmetry_fold: bool = False,
        grad_probe_every: int = 0,
        **kwargs: Any,
    ) -> None:
        del sampler, num_noisy, symmetry_fold, grad_probe_every  # diffusion options (docstring)
        if int(iterations) < 0:
            raise ValueError(f"iterations must be >= 0, got {iterations}")
        if int(iterations) > 0 and denoiser is None:
            raise ValueError(
                "iterative regression (iterations > 0) needs a refinement network (module.denoiser)"
            )
        kwargs["anchor"] = False
        kwargs["aux_weight"] = 0.0
        super().__init__(diffusion, denoiser if int(iterations) > 0 else nn.Identity(), **kwargs)
        self.iterations = int(iterations)
        self.translation_weight = float(translation_weight)
        if self.iterations > 0 and hasattr(self.encoder, "decode_in_training"):
            self.encoder.decode_in_training = True  # the refinement starts from the decoded rotation

    # ------------------------------------------------------------------ the estimate
    def refine(self, x: Tensor, k: int, feature: Tensor) -> Tensor:
        """One refinement step of estimates ``x (B, n, n)``: ``x · Exp(f(x, k, feature))``."""
        level = torch.full((x.shape[0], 1), float(k), dtype=x.dtype, device=x.device)
        delta = self.denoiser(self.pose_features(x).unsqueeze(1), level, feature)[:, 0]
        return self.group.rplus(x, delta)

    def estimates(self, enc: Encoding, *, detach: bool = False) -> list[Tensor]:
        """The K + 1 estimates ``(B, n, n)``: the head's, then each refinement."""
        x = self.anchor_pose(enc)
        out = [x]
        for k in range(self.iterations):
            x = self.refine(x.detach() if detach else x, k, enc.feature)
            out.append(x)
        return out

    def pose_loss(self, batch: dict[str, Tensor], x: Tensor) -> Tensor:
        """Symmetry-aware loss of estimates ``x (B, n, n)`` (module docstring), batch mean."""
        loss = symmetric_rotation_loss(batch, x[..., :3, :3]).mean()
        if x.shape[-1] == 4:
            loss = (
                loss
                + self.translation_weight * (x[..., :3, 3] - batch["pose"][:, :3, 3]).square().sum(-1).mean()
            )
        return loss

    # ------------------------------------------------------------------ training
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        enc = self.encode_full(batch[self.cond_key], pose=batch["pose"])
        losses = [self.anchor_loss(batch, enc).mean()]
        if self.iterations:
            xs = self.estimates(enc, detach=True)
            losses += [self.pose_loss(batch, x) for x in xs[1:]]
        loss = torch.stack(losses).mean() + self.side_losses(batch, enc, "train")
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite training loss {loss.item()} at step {self.global_step}")
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["pose"].shape[0])
        self.loss_history.append(float(loss.detach()))
        return loss

    @torch.no_grad()
    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """``val/loss``: the symmetry-aware loss of the final estimate on held-out inputs."""
        enc = self.encode_full(batch[self.cond_key])
        loss = self.pose_loss(batch, self.estimates(enc)[-1])
        self.log("val/loss", loss, prog_bar=True, batch_size=batch["pose"].shape[0])
        self.side_losses(batch, enc, "val")
        return loss

    # ------------------------------------------------------------------ "sampling"
    @torch.no_grad()
    def sample(
        self,
        cond: Any,
        num_samples: int,
        num_steps: int | None = None,
        *,
        sampler: Any = None,
        generator: torch.Generator | None = None,
        trajectory: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """The one estimate per input repeated ``num_samples`` times, ``(B, N, n, n)`` (with
        ``trajectory``: also the K + 1 iterates, ``(K + 1, B, N, n, n)``); ``num_steps``, ``sampler``
        and ``generator`` are ignored (a regression is deterministic)."""
        xs = self.estimates(self.encode_full(cond))
        n = int(num_samples)
        rep = [x.unsqueeze(1).expand(-1, n, -1, -1).contiguous() for x in xs]
        if trajectory:
            return rep[-1], torch.stack(rep)
        return rep[-1]
