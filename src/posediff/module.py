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

import os
from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn
from torch.profiler import record_function

from .diffusion import Diffusion, Sampler
from .lie._pose import make_pose
from .nn.pose_encoder import Encoding
from .symmetry import SHAPES, set_chordal_sq, symsol_chordal_sq, symsol_nearest_symmetry

#: the key of the run configuration in the module's hyperparameters (and in its checkpoints)
CONFIG_HPARAM = "posediff_config"


def compile_problem() -> str | None:
    """Why ``torch.compile`` (inductor) cannot run here, or ``None``: on the CPU it needs a C++ compiler."""
    import shutil

    if not any(shutil.which(c) for c in (os.environ.get("CXX", "g++"), "g++", "clang++", "c++")):
        return "inductor needs a C++ compiler on the CPU and none is on PATH (apt install g++)"
    return None


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
        anchor: the anchored denoiser (module docstring); needs an encoder that returns an
            :class:`~posediff.nn.Encoding` (``posediff.nn.PoseEncoder``).
        aux_weight: weight of the symmetry-aware regression loss on the anchor (rotation:
            ``min_S ‖R̂ − R·S‖²_F``; translation: squared error); 0 = diffusion loss only. Without
            an anchor and with ``aux_weight=0``, a pose-estimating encoder's head is trained as a
            *linear probe* on the detached feature (it never changes the encoder): ``anchor_deg``
            then tells whether the paper's encoder sees orientation.
        locate_weight: weight of the locator's translation regression (locate-then-crop encoders).
        symmetry_fold: the symmetry-folded denoiser (module docstring); needs ``anchor`` and the
            invariant rotation head.
        denoiser_lr: the denoiser's own Adam rate (``None``: ``lr``), decayed by the same factor — a
            from-scratch image encoder wants a smaller step than the MLP denoiser (the toys' 1e-3).
        grad_probe_every: every N training steps, log the encoder's gradient norm from the rotation
            and the translation parts of the diffusion loss separately (two extra backward passes;
            0 = never).
    """

    POSE_INPUTS = ("tangent", "matrix")
    #: Adam's update: ``default`` (PyTorch's choice: a for-loop over tensors on the CPU), ``foreach``
    #: (multi-tensor), ``fused`` (one fused kernel; CPU and CUDA) — the same arithmetic
    OPTIMIZER_IMPLS = ("default", "foreach", "fused")

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
        anchor: bool = False,
        aux_weight: float = 0.0,
        locate_weight: float = 1.0,
        symmetry_fold: bool = False,
        grad_probe_every: int = 0,
        denoiser_lr: float | None = None,
        optimizer_impl: str = "default",
        channels_last: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__()
        if optimizer_impl not in self.OPTIMIZER_IMPLS:
            raise ValueError(
                f"unknown optimizer_impl {optimizer_impl!r}; choose one of: {', '.join(self.OPTIMIZER_IMPLS)}"
            )
        for key, flag in (
            ("channels_last", channels_last),
            ("compile", compile),
            ("symmetry_fold", symmetry_fold),
        ):
            if not isinstance(flag, bool):  # bool("abc") is True: a typo would switch the lever on
                raise ValueError(f"module.{key} must be true or false, got {flag!r}")
        self.optimizer_impl = optimizer_impl
        self.channels_last = channels_last
        self.compile_networks = compile
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
        self.anchor = bool(anchor)
        self.aux_weight = float(aux_weight)
        self.locate_weight = float(locate_weight)
        self.grad_probe_every = int(grad_probe_every)
        self.denoiser_lr = None if denoiser_lr is None else float(denoiser_lr)
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
        #: whether the encoder places training crops by the target (``forward(image, pose=...)``)
        self._encoder_takes_pose = _takes_pose(self.encoder)
        #: weight of the translation's squared error in :meth:`anchor_loss` (the regression baselines set it)
        self.translation_weight = 1.0
        if hasattr(self.encoder, "decode_in_training"):  # decode the invariant head in training only if used
            self.encoder.decode_in_training = self.anchor
        n = int(self.group.matrix_dim)
        #: width of the anchor packed behind the feature in the condition (0 without an anchor)
        #: (with ``symmetry_fold`` one more entry: the index in SYMSOL's SHAPES of the classified shape)
        self.anchor_width = (n * n + int(self.symmetry_fold)) if self.anchor else 0
        #: the training loss of every step (floats), for run summaries; stored in checkpoints
        self.loss_history: list[float] = []
        #: the global RNG states of a checkpoint being resumed, restored in :meth:`on_train_start`
        self._rng_to_restore: dict[str, Any] | None = None

    @property
    def group(self):  # noqa: ANN201 - LieGroup
        return self.diffusion.group

    # ------------------------------------------------------------------ the network
    def encode(self, cond: Any) -> Tensor:
        """The per-input condition the denoiser reads, computed once per input: the feature, with the
        anchor pose packed behind it when ``anchor`` is on (``(B, F + n²)``)."""
        return self.pack(self.encode_full(cond))

    def encode_full(self, cond: Any, pose: Tensor | None = None) -> Encoding:
        """The encoder's whole output as an :class:`~posediff.nn.Encoding` (a plain encoder's
        feature gets the identity as its anchor). ``pose``: the training target, for encoders that
        place training crops by it."""
        if isinstance(self.encoder, nn.Identity):
            out = cond
        else:
            out = self.encoder(cond, pose=pose) if self._encoder_takes_pose else self.encoder(cond)
        if isinstance(out, Encoding):
            return out
        if self.anchor:
            raise ValueError(
                "module.anchor=true needs an encoder that estimates a pose (posediff.nn.PoseEncoder: encoder=pose)"
            )
        return Encoding(out, rotation=None)  # type: ignore[arg-type]

    def anchor_pose(self, enc: Encoding) -> Tensor:
        """The anchor as a group element ``(B, n, n)`` (``[R̂ | t̂]`` for 4×4 groups)."""
        n = int(self.group.matrix_dim)
        if enc.rotation is None and enc.embedding is not None:  # an invariant head not decoded in training
            R = self.encoder.decode(enc.embedding, enc.shape_logits)
            enc.rotation = R if enc.ray is None else enc.ray @ R
        if n == 3:
            return enc.rotation
        R = enc.rotation
        t = enc.translation if enc.translation is not None else R.new_zeros(*R.shape[:-2], 3)
        return make_pose(R, t)

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

    # ------------------------------------------------------------------ training
    def on_fit_start(self) -> None:
        """The speed levers that change how, not what, the networks compute (benchmarks/train_step.py):
        ``channels_last`` puts the encoder's conv weights (and so its activations) in channels-last order;
        ``compile`` compiles the encoder's and the denoiser's forward (and so backward) with
        ``torch.compile`` in place (state-dict keys unchanged) — where the backend cannot run (no C++
        compiler for inductor on the CPU) a warning says so and training stays eager."""
        if self.channels_last and not isinstance(self.encoder, nn.Identity):
            self.encoder.to(memory_format=torch.channels_last)
        if self.compile_networks:
            problem = compile_problem()
            if problem is not None:
                import warnings

                warnings.warn(f"module.compile=true ignored: {problem}; training eagerly", stacklevel=1)
                return
            if not isinstance(self.encoder, nn.Identity):
                self.encoder.compile()
            self.denoiser.compile()

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

    def side_losses(self, batch: dict[str, Tensor], enc: Encoding, stage: str) -> Tensor:
        """The locator's regression and the anchor's symmetry-aware loss (weighted), logged per part;
        the anchor's symmetric rotation error in degrees is logged whenever there is an anchor (the
        probe "does the encoder see orientation")."""
        bs = batch["pose"].shape[0]
        total = torch.zeros((), device=batch["pose"].device)
        pose = batch["pose"]
        if enc.located is not None:
            locate = (enc.located - pose[:, :3, 3]).square().sum(-1).mean()
            self.log(f"{stage}/locate_loss", locate, batch_size=bs)
            total = total + self.locate_weight * locate
        has_head = enc.rotation is not None or enc.embedding is not None
        if not has_head or ("shape" not in batch and "symmetries" not in batch):
            return total
        probe = not self.anchor and self.aux_weight == 0 and hasattr(self.encoder, "head_pose")
        if probe:  # the pose head as a linear probe: trained on the detached feature, never the encoder
            R, t, emb, logits = self.encoder.head_pose(
                enc.feature.detach(), enc.ray, enc.crop_translation, enc.log_size
            )
            enc = Encoding(
                enc.feature, R, t, enc.located, enc.crop_translation, enc.ray, emb, logits, enc.log_size
            )
        rotation_loss = None  # min_S ‖R̂ − R·S‖²_F, computed once for the log and (6-D head) the loss
        if enc.rotation is not None:
            trains = (self.aux_weight > 0 or probe) and enc.embedding is None
            rotation_loss = symmetric_rotation_loss(batch, enc.rotation if trains else enc.rotation.detach())
            deg = torch.rad2deg(_chordal_to_angle(rotation_loss.detach()))
            self.log(f"{stage}/anchor_deg", deg.mean(), prog_bar=stage == "val", batch_size=bs)
            if stage == "val":
                for k in batch["shape"].unique().tolist() if "shape" in batch else []:
                    sel = batch["shape"] == k
                    self.log(f"val/anchor_deg_{SHAPES[int(k)]}", deg[sel].mean(), batch_size=int(sel.sum()))
        if self.aux_weight > 0 or probe:
            aux = self.anchor_loss(batch, enc, rotation_loss=rotation_loss).mean()
            self.log(f"{stage}/{'probe' if probe else 'aux'}_loss", aux, batch_size=bs)
            total = total + (1.0 if probe else self.aux_weight) * aux
        return total

    def anchor_loss(
        self, batch: dict[str, Tensor], enc: Encoding, rotation_loss: Tensor | None = None
    ) -> Tensor:
        """The symmetry-aware loss of the encoder's pose per input ``(B,)``: the invariant head's
        embedding loss, or ``min_S ‖R̂ − R·S‖²_F`` (``rotation_loss`` when the caller has it already);
        plus the translation's squared error."""
        pose = batch["pose"]
        if enc.embedding is not None:
            loss = self.encoder.embedding_loss(enc, batch["shape"], pose[..., :3, :3])
        else:
            loss = (
                rotation_loss if rotation_loss is not None else symmetric_rotation_loss(batch, enc.rotation)
            )
        if enc.translation is not None and pose.shape[-1] == 4:
            loss = loss + self.translation_weight * (enc.translation - pose[:, :3, 3]).square().sum(-1)
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

    @property
    def config(self) -> dict[str, Any] | None:
        """The resolved run configuration (``posediff fit`` sets it): the module's hyperparameters
        (``self.hparams["posediff_config"]``, saved by Lightning's ``save_hyperparameters``), stored in
        every checkpoint and what :meth:`load_from_checkpoint` rebuilds the module from."""
        value = self.hparams.get(CONFIG_HPARAM) if hasattr(self, "_hparams") else None
        return value if isinstance(value, dict) else None

    @config.setter
    def config(self, value: dict[str, Any] | None) -> None:
        self.save_hyperparameters({CONFIG_HPARAM: value}, logger=value is not None)

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: Any,
        map_location: Any = None,
        hparams_file: Any = None,
        strict: bool | None = None,
        **kwargs: Any,
    ) -> "PoseDiffusionModule":
        """The trained module of a ``posediff fit`` checkpoint, in eval mode — Lightning's usual entry
        point, here through :func:`posediff.load_checkpoint`: ``torch.load(weights_only=True)``, the
        stored run config checked against posediff's allow-list before anything is built (never
        ``cls(**hparams)`` on a file's contents). ``hparams_file`` and keyword overrides are refused
        (the architecture is the checkpoint's); ``strict`` must not be False."""
        from .checkpoint import CheckpointError, load_checkpoint

        if hparams_file is not None or kwargs or strict is False:
            raise TypeError(
                "posediff checkpoints are rebuilt from their stored, allow-listed run config: "
                "hparams_file, keyword overrides and strict=False are not supported"
            )
        module = load_checkpoint(
            checkpoint_path, map_location=map_location if map_location is not None else "cpu"
        )
        if not isinstance(module, cls):
            raise CheckpointError(f"{checkpoint_path} holds a {type(module).__name__}, not a {cls.__name__}")
        return module

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.config is not None:
            checkpoint["posediff_config"] = self.config
            checkpoint["posediff_diffusion"] = self.diffusion.describe()
        # exact resume (with the training loader's position, which Lightning stores): the loss curve
        # so far and the global RNG streams the training noise is drawn from
        checkpoint[LOSS_HISTORY_KEY] = torch.tensor(self.loss_history, dtype=torch.float64)
        checkpoint[RNG_KEY] = rng_state()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        history = checkpoint.get(LOSS_HISTORY_KEY)
        if history is not None:
            self.loss_history = [float(v) for v in history.tolist()]
        # applied when training starts (after Lightning has set up the training data), never when a
        # checkpoint is only loaded for evaluation
        self._rng_to_restore = checkpoint.get(RNG_KEY)

    def on_train_start(self) -> None:
        state, self._rng_to_restore = getattr(self, "_rng_to_restore", None), None
        if state is not None:
            set_rng_state(state)

    def configure_optimizers(self) -> dict[str, Any]:
        den = {id(p) for p in self.denoiser.parameters()}
        rest = [p for p in self.parameters() if p.requires_grad and id(p) not in den]
        params: list[dict[str, Any]] = [{"params": rest, "lr": self.lr}]
        den_params = [p for p in self.denoiser.parameters() if p.requires_grad]
        if den_params:
            params.append({"params": den_params, "lr": self.denoiser_lr or self.lr})
        params = [g for g in params if g["params"]]
        impl: dict[str, bool] = {"foreach": {"foreach": True}, "fused": {"fused": True}}.get(
            self.optimizer_impl, {}
        )
        if self.weight_decay > 0:
            opt: torch.optim.Optimizer = torch.optim.AdamW(
                params, lr=self.lr, weight_decay=self.weight_decay, **impl
            )
        else:
            opt = torch.optim.Adam(params, lr=self.lr, **impl)
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


#: checkpoint keys of the training loss so far (float64 tensor) and of the global RNG states
LOSS_HISTORY_KEY = "posediff_loss_history"
RNG_KEY = "posediff_rng"


def rng_state() -> dict[str, Any]:
    """The global RNG states (torch CPU, CUDA when initialised, numpy, Python) as plain tensors and
    containers (``torch.load(weights_only=True)`` reads them)."""
    import random

    import numpy as np

    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "kind": str(kind),
            "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached": float(cached),
        },
        "python": {"version": int(version), "internal": list(internal), "gauss_next": gauss_next},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    import random

    import numpy as np

    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    keys = n["keys"].numpy().astype(np.uint32)
    np.random.set_state((n["kind"], keys, n["pos"], n["has_gauss"], n["cached"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        cuda = state["cuda"]
        if len(cuda) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda)


def _chordal_to_angle(chordal_sq: Tensor) -> Tensor:
    """Geodesic angle (radians) of a squared chordal distance ``8 sin²(θ/2)``."""
    return 2.0 * torch.asin((chordal_sq.clamp_min(0.0) / 8.0).sqrt().clamp(max=1.0))


def symmetric_rotation_loss(batch: dict[str, Tensor], R: Tensor) -> Tensor:
    """``min_S ‖R − R_gt·S‖²_F`` per input (``(B,)``, or ``(B, N)`` for ``R (B, N, 3, 3)``) against the
    rotation of the batch's ``pose`` (the network's frame: allocentric for BOP crops) over the input's
    symmetries: the batch's padded ``symmetries`` / ``symmetries_mask`` (BOP ``models_info``) or its
    SYMSOL ``shape`` ids (exact groups, cone / cylinder in closed form)."""
    R_gt = batch["pose"][..., :3, :3].to(R.dtype)
    if "symmetries" in batch:
        return set_chordal_sq(R, R_gt, batch["symmetries"].to(R.dtype), batch["symmetries_mask"])
    if "shape" in batch:
        return symsol_chordal_sq(batch["shape"], R, R_gt)
    raise ValueError(
        "the symmetry-aware loss needs the batch's symmetries: SYMSOL shape ids ('shape') or BOP "
        "'symmetries'; this data has neither"
    )


def _takes_pose(encoder: nn.Module) -> bool:
    """Whether ``encoder.forward`` accepts the training target (``pose=``) to place its crops."""
    import inspect

    try:
        return "pose" in inspect.signature(encoder.forward).parameters
    except (TypeError, ValueError):
        return False
