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

**Anchored denoiser** (``anchor=True``, beyond the paper): with a
:class:`~posediff.nn.PoseEncoder`, the encoder also estimates one pose ``X̂`` per input and the
denoiser sees the noisy pose *relative to it*, ``Log(X̂⁻¹ X̃)`` (on R³×SO(3) that is
``(t̃ − t̂, Log(R̂ᵀR̃))``). The score is a right-trivialised tangent at ``X̃``, which a left
multiplication leaves unchanged, so the target, the samplers and the prior are the paper's; with
``X̂ = I`` the network is exactly the paper's. The anchor travels packed behind the feature in the
condition tensor (``(B, F + n²)``), so samplers, ``modes()``, ``log_likelihood()``, eval and predict
see the same interface. It is trained through the diffusion loss alone (``aux_weight=0``: no
symmetry labels) or with the symmetry-aware regression loss as an auxiliary term (``aux_weight``).
A locate-then-crop encoder's locator is trained by regression on the translation (``locate_weight``).

**Symmetry-folded denoiser** (``symmetry_fold=True``, beyond the paper; needs the invariant head,
whose classifier names the shape): the noisy pose is first moved to its equivalent nearest the anchor,
``X̃·S*`` with ``S* = argmax_S tr(R̂ᵀR̃·S)`` over the shape's symmetries
(:func:`~posediff.symmetry.nearest_symmetry`), the network sees ``Log(X̂⁻¹X̃S*)`` and its output is
carried back to ``X̃`` by ``Ad(S*)``. For a density with ``p(X·S) = p(X)`` the right-trivialised
score obeys ``s(X·S) = Ad(S)⁻¹ s(X)``, so this is exact — the denoiser models one mode around the
anchor instead of all 12/24/60 (or a circle of them), and every sample lands on one of the
equivalent poses by construction. It uses the symmetry labels, as the invariant head does.
"""

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn
from torch.profiler import record_function

from ..diffusion import Diffusion, Sampler
from ..lie._pose import make_pose
from ..nn.pose_encoder import Encoding
from ..symmetry import SHAPES, symsol_nearest_symmetry
from .base import PoseModule


class PoseDiffusionModule(PoseModule):
    """Score-based pose diffusion on a Lie group, trained with denoising score matching (paper Alg. 1).

    Takes :class:`~posediff.models.base.PoseModule`'s arguments and:

    Args:
        diffusion: the forward process and objective.
        denoiser: ``net(tangent (B,N,dim), noise_level (B,N), feature (B,F)) → (B,N,dim)``.
        sampler: a factory ``sampler(diffusion) → Sampler`` (Hydra ``_partial_: true``).
        num_noisy: noisy poses per input per step (paper: 256).
        anchor: the anchored denoiser (module docstring); needs an encoder that returns an
            :class:`~posediff.nn.Encoding` (``posediff.nn.PoseEncoder``).
        aux_weight: weight of the symmetry-aware regression loss on the anchor (rotation:
            ``min_S ‖R̂ − R·S‖²_F``; translation: squared error); 0 = diffusion loss only. Without
            an anchor and with ``aux_weight=0``, a pose-estimating encoder's head is trained as a
            *linear probe* on the detached feature (it never changes the encoder): ``anchor_deg``
            then tells whether the paper's encoder sees orientation.
        symmetry_fold: the symmetry-folded denoiser (module docstring); needs ``anchor`` and the
            invariant rotation head.
        grad_probe_every: every N training steps, log the encoder's gradient norm from the rotation
            and the translation parts of the diffusion loss separately (two extra backward passes;
            0 = never).
    """

    def __init__(
        self,
        diffusion: Diffusion,
        denoiser: nn.Module,
        sampler: Callable[[Diffusion], Sampler],
        *,
        num_noisy: int = 256,
        anchor: bool = False,
        aux_weight: float = 0.0,
        symmetry_fold: bool = False,
        grad_probe_every: int = 0,
        **kwargs: Any,
    ) -> None:
        if not isinstance(symmetry_fold, bool):  # bool("abc") is True: a typo would switch the lever on
            raise ValueError(f"module.symmetry_fold must be true or false, got {symmetry_fold!r}")
        super().__init__(diffusion, denoiser, anchor=anchor, aux_weight=aux_weight, **kwargs)
        self.sampler = sampler(diffusion) if not isinstance(sampler, Sampler) else sampler
        self.num_noisy = int(num_noisy)
        self.grad_probe_every = int(grad_probe_every)
        if (
            self.anchor
            and self.aux_weight == 0
            and getattr(self.encoder, "rotation_head", "6d") == "invariant"
        ):
            raise ValueError(
                "the invariant rotation head is trained only by the symmetry-aware loss: with module.anchor=true "
                "set module.aux_weight > 0, or use encoder.rotation_head=6d for an anchor trained by diffusion alone"
            )
        self.symmetry_fold = symmetry_fold
        if symmetry_fold and not (
            self.anchor and getattr(self.encoder, "rotation_head", None) == "invariant"
        ):
            raise ValueError(
                "module.symmetry_fold=true needs module.anchor=true and the invariant head's shape classifier "
                "(encoder=pose encoder.rotation_head=invariant); otherwise set module.symmetry_fold=false"
            )
        n = int(self.group.matrix_dim)
        #: width of the anchor packed behind the feature in the condition (0 without an anchor)
        #: (with ``symmetry_fold`` one more entry: the index in SYMSOL's SHAPES of the classified shape)
        self.anchor_width = (n * n + int(self.symmetry_fold)) if self.anchor else 0

    def encode(self, cond: Any) -> Tensor:
        """The per-input condition the denoiser reads, computed once per input: the feature, with the
        anchor pose packed behind it when ``anchor`` is on (``(B, F + n²)``)."""
        return self.pack(self.encode_full(cond))

    def pack(self, enc: Encoding) -> Tensor:
        """The condition tensor of an encoding: the feature, or ``[feature | anchor entries]``."""
        if not self.anchor:
            return enc.feature
        parts = [enc.feature, self.anchor_pose(enc).flatten(-2)]
        if self.symmetry_fold:
            to_global = torch.tensor(
                [SHAPES.index(x) for x in self.encoder.shapes], device=enc.feature.device
            )
            parts.append(to_global[enc.shape_logits.detach().argmax(-1)].to(enc.feature.dtype)[:, None])
        return torch.cat(parts, dim=-1)

    def unpack(self, cond: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(feature, anchor (B, n, n) or None)`` of a condition tensor made by :meth:`pack`."""
        if not self.anchor:
            return cond, None
        n = int(self.group.matrix_dim)
        anchor = cond[..., -self.anchor_width :][..., : n * n].unflatten(-1, (n, n))
        return cond[..., : -self.anchor_width], anchor

    def folded_shapes(self, cond: Tensor) -> Tensor:
        """The shape indices (into SYMSOL's SHAPES) packed in a ``symmetry_fold`` condition, ``(B,)``."""
        return cond[..., -1].round().long()

    def forward(self, x_noisy: Tensor, sigma: Tensor, feature: Tensor) -> Tensor:
        """Raw network output at noisy poses ``x_noisy (B, N, n, n)`` with levels ``sigma (B, N)``;
        ``feature`` is the condition of :meth:`encode` (with the anchor when ``anchor`` is on)."""
        level = self.diffusion.schedule.level(sigma)
        feature, anchor = self.unpack(cond := feature)
        if anchor is None:
            return self.denoiser(self.pose_features(x_noisy), level, feature)
        g = self.group
        x_rel = g.compose(g.inverse(anchor).unsqueeze(-3), x_noisy)
        if not self.symmetry_fold:
            return self.denoiser(self.pose_features(x_rel), level, feature)
        S = symsol_nearest_symmetry(self.folded_shapes(cond), x_rel[..., :3, :3].detach())
        fold = S if int(g.matrix_dim) == 3 else make_pose(S, S.new_zeros(*S.shape[:-2], 3))
        out = self.denoiser(self.pose_features(g.compose(x_rel, fold)), level, feature)
        return (g.adjoint(fold) @ out.unsqueeze(-1)).squeeze(-1)

    def denoise_fn(self) -> Callable[[Tensor, Tensor, Tensor], Tensor]:
        """The ``denoise_fn(x, sigma, feature)`` the samplers call."""
        return self.forward

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        # the named ranges split a step in torch.profiler (benchmarks/train_step.py); ~µs when off
        with record_function("posediff.encoder"):
            enc = self.encode_full(batch[self.cond_key], pose=batch["pose"])
        with record_function("posediff.perturb"):
            noisy = self.diffusion.perturb(batch["pose"], num_noisy=self.num_noisy)
        with record_function("posediff.denoiser"):
            out = self(noisy.x_noisy, noisy.sigma, self.pack(enc))
        with record_function("posediff.losses"):
            diffusion_loss = self.diffusion.loss(out, noisy)
            bs = batch["pose"].shape[0]
            loss = diffusion_loss + self.side_losses(batch, enc, "train")
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite training loss {loss.item()} at step {self.global_step}")
        if self.grad_probe_every > 0 and self.global_step % self.grad_probe_every == 0:
            self._probe_gradients(out, noisy)
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        if loss is not diffusion_loss:
            self.log("train/diffusion_loss", diffusion_loss, batch_size=bs)
        self.loss_history.append(float(loss.detach()))
        return loss

    def _probe_gradients(self, out: Tensor, noisy: Any) -> None:
        """Log ``grad/encoder_rotation`` and ``grad/encoder_translation``: the encoder's gradient norm
        from the rotation and the translation parts of the diffusion loss."""
        params = [p for p in self.encoder.parameters() if p.requires_grad]
        if not params:
            return
        parts = self.diffusion.loss_parts(out, noisy)
        for name, part in parts.items():
            grads = torch.autograd.grad(part, params, retain_graph=True, allow_unused=True)
            norm = torch.sqrt(sum((g.square().sum() for g in grads if g is not None), torch.zeros(())))
            self.log(f"grad/encoder_{name}", norm, batch_size=out.shape[0])

    @torch.no_grad()
    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """The training objective on held-out inputs (``val/loss``: what "best" checkpoints track;
        ``val/rotation_loss`` its rotation part; ``val/anchor_deg`` the anchor's error)."""
        enc = self.encode_full(batch[self.cond_key])
        feature = self.pack(enc)
        gen = torch.Generator(device=feature.device).manual_seed(1000 + batch_idx)
        noisy = self.diffusion.perturb(batch["pose"], num_noisy=self.num_noisy, generator=gen)
        out = self(noisy.x_noisy, noisy.sigma, feature)
        loss = self.diffusion.loss(out, noisy)
        bs = batch["pose"].shape[0]
        self.log("val/loss", loss, prog_bar=True, batch_size=bs)
        parts = self.diffusion.loss_parts(out, noisy)
        if "rotation" in parts:
            self.log("val/rotation_loss", parts["rotation"], batch_size=bs)
        self.side_losses(batch, enc, "val")
        return loss

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


__all__ = ["PoseDiffusionModule"]
