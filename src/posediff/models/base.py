"""``PoseModule``: what posediff's two kinds of pose model share — the diffusion model
(:class:`~posediff.models.PoseDiffusionModule`) and the regression baselines
(:class:`~posediff.models.PoseRegressionModule`) are its siblings.

Shared are the encoder (the condition → a feature, and with a :class:`~posediff.nn.PoseEncoder` one pose
estimate, the *anchor*), the side losses (the locator's regression, the anchor's symmetry-aware loss or
linear probe, :mod:`posediff.models.losses`), the stored run configuration and what a checkpoint holds
beside the weights (:mod:`posediff.models.checkpoint`), the speed levers and the optimiser (Adam with
an exponential decay over the second half of training, paper §5).
"""

from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from ..hardware import compile_problem
from ..lie._pose import make_pose
from ..nn.pose_encoder import Encoding
from ..nn.pose_input import POSE_INPUTS, pose_features
from ..symmetry import SHAPES
from .checkpoint import (
    CONFIG_KEY,
    DIFFUSION_KEY,
    LOSS_HISTORY_KEY,
    RNG_KEY,
    load_checkpoint,
    rng_state,
    set_rng_state,
)
from .losses import chordal_to_angle, symmetric_rotation_loss


class PoseModule(L.LightningModule):
    """The shared part of a pose model (module docstring). Subclasses add the training step, the
    validation step and ``sample(cond, num_samples, ...) → (B, N, n, n)``.

    Args:
        diffusion: the forward process (the regression baselines use it only for its group).
        denoiser: the network after the encoder (the MLP denoiser; a regression's refinement network).
        encoder: maps ``batch[cond_key]`` to the ``(B, F)`` feature (default: identity).
        lr, lr_final, decay_start: Adam at ``lr``, exponential decay to ``lr_final`` from the fraction
            ``decay_start`` of ``trainer.max_steps`` to the end (paper: 1e-4 → 1e-5 over the second half).
        weight_decay: > 0 uses AdamW (the authors' code: 1e-4).
        pose_input: what the denoiser sees of a pose: ``"tangent"`` (``Log X̃``, the paper) or
            ``"matrix"`` (the top 3 rows of ``X̃``, flattened); :func:`posediff.nn.pose_input_dim`.
        anchor, aux_weight: whether the denoiser is anchored on the encoder's pose, and the weight of
            the anchor's symmetry-aware loss (:meth:`side_losses`).
        locate_weight: weight of the locator's translation regression (locate-then-crop encoders:
            ``encoder.crop_size`` set); 0 leaves the locator untrained.
        denoiser_lr: the denoiser's own Adam rate (``None``: ``lr``), decayed by the same factor.
        optimizer_impl, channels_last, compile: speed levers that keep the arithmetic
            (``benchmarks/results/train_step.md``).
    """

    POSE_INPUTS = POSE_INPUTS
    #: Adam's update: ``default`` (PyTorch's choice: a for-loop over tensors on the CPU), ``foreach``
    #: (multi-tensor), ``fused`` (one fused kernel; CPU and CUDA) — the same arithmetic
    OPTIMIZER_IMPLS = ("default", "foreach", "fused")

    def __init__(
        self,
        diffusion: Any,
        denoiser: nn.Module,
        *,
        encoder: nn.Module | None = None,
        cond_key: str = "cond",
        lr: float = 1e-4,
        lr_final: float = 1e-5,
        decay_start: float = 0.5,
        weight_decay: float = 0.0,
        pose_input: str = "tangent",
        anchor: bool = False,
        aux_weight: float = 0.0,
        locate_weight: float = 1.0,
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
        for key, flag in (("channels_last", channels_last), ("compile", compile)):
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
        self.cond_key = cond_key
        self.lr = float(lr)
        self.lr_final = float(lr_final)
        self.decay_start = float(decay_start)
        self.weight_decay = float(weight_decay)
        self.anchor = bool(anchor)
        self.aux_weight = float(aux_weight)
        self.locate_weight = float(locate_weight)
        self.denoiser_lr = None if denoiser_lr is None else float(denoiser_lr)
        #: whether the encoder places training crops by the target (``forward(image, pose=...)``)
        self._encoder_takes_pose = _takes_pose(self.encoder)
        #: weight of the translation's squared error in :meth:`anchor_loss` (the regression baselines set it)
        self.translation_weight = 1.0
        if hasattr(self.encoder, "decode_in_training"):  # decode the invariant head in training only if used
            self.encoder.decode_in_training = self.anchor
        #: the training loss of every step (floats), for run summaries; stored in checkpoints
        self.loss_history: list[float] = []
        #: the global RNG states of a checkpoint being resumed, restored in :meth:`on_train_start`
        self._rng_to_restore: dict[str, Any] | None = None

    @property
    def group(self):  # noqa: ANN201 - LieGroup
        return self.diffusion.group

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

    def pose_features(self, x_noisy: Tensor) -> Tensor:
        """What the denoiser sees of ``x_noisy (..., n, n)``: ``(..., pose_input_dim)``."""
        return pose_features(self.group, x_noisy, self.pose_input)

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
            deg = torch.rad2deg(chordal_to_angle(rotation_loss.detach()))
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

    @property
    def config(self) -> dict[str, Any] | None:
        """The resolved run configuration (``posediff fit`` sets it): the module's hyperparameters
        (``self.hparams[CONFIG_KEY]``, saved by Lightning's ``save_hyperparameters``), stored in
        every checkpoint and what :meth:`load_from_checkpoint` rebuilds the module from."""
        value = self.hparams.get(CONFIG_KEY) if hasattr(self, "_hparams") else None
        return value if isinstance(value, dict) else None

    @config.setter
    def config(self, value: dict[str, Any] | None) -> None:
        self.save_hyperparameters({CONFIG_KEY: value}, logger=value is not None)

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: Any,
        map_location: Any = None,
        hparams_file: Any = None,
        strict: bool | None = None,
        **kwargs: Any,
    ) -> "PoseModule":
        """The trained module of a ``posediff fit`` checkpoint, in eval mode — Lightning's usual entry
        point, here through :func:`posediff.load_checkpoint`: ``torch.load(weights_only=True)``, the
        stored run config checked against posediff's allow-list before anything is built (never
        ``cls(**hparams)`` on a file's contents). ``hparams_file`` and keyword overrides are refused
        (the architecture is the checkpoint's); ``strict`` must not be False."""
        if hparams_file is not None or kwargs or strict is False:
            raise TypeError(
                "posediff checkpoints are rebuilt from their stored, allow-listed run config: "
                "hparams_file, keyword overrides and strict=False are not supported"
            )
        return load_checkpoint(
            checkpoint_path, expected=cls, map_location=map_location if map_location is not None else "cpu"
        )

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.config is not None:
            checkpoint[CONFIG_KEY] = self.config
            checkpoint[DIFFUSION_KEY] = self.diffusion.describe()
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


def _takes_pose(encoder: nn.Module) -> bool:
    """Whether ``encoder.forward`` accepts the training target (``pose=``) to place its crops."""
    import inspect

    try:
        return "pose" in inspect.signature(encoder.forward).parameters
    except (TypeError, ValueError):
        return False


__all__ = ["PoseModule"]
