"""posediff's pose models: :class:`PoseDiffusionModule` (the paper's score model) and
:class:`PoseRegressionModule` (its regression baselines), siblings on :class:`PoseModule`, with their
checkpoints (:mod:`.checkpoint`: safe loading) and export (:mod:`.export`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from . import checkpoint as _checkpoint
from .base import PoseModule
from .checkpoint import (
    CONFIG_KEY,
    CheckpointError,
    check_compatible,
    checkpoint_group,
    checkpoint_shapes,
    read_checkpoint,
)
from .diffusion import PoseDiffusionModule
from .losses import symmetric_rotation_loss
from .regression import PoseRegressionModule


def load_checkpoint(
    path: str | os.PathLike[str],
    *,
    map_location: Any = "cpu",
    group: str | None = None,
    shapes: Sequence[str] | None = None,
) -> PoseModule:
    """The trained pose model (diffusion or regression) of a ``posediff fit`` checkpoint, in eval mode
    (:func:`posediff.models.checkpoint.load_checkpoint` with ``expected=PoseModule``). ``group`` /
    ``shapes``: refuse (one line) a checkpoint trained on another group or without those shapes.
    ``module.config`` holds the stored run configuration."""
    return _checkpoint.load_checkpoint(
        path, expected=PoseModule, map_location=map_location, group=group, shapes=shapes
    )


def module_from_checkpoint(ckpt: dict[str, Any], path: str | os.PathLike[str] = "checkpoint") -> PoseModule:
    """The pose model of a checkpoint dict read with :func:`read_checkpoint` (eval mode)."""
    return _checkpoint.module_from_checkpoint(ckpt, path, expected=PoseModule)


__all__ = [
    "CONFIG_KEY",
    "CheckpointError",
    "PoseDiffusionModule",
    "PoseModule",
    "PoseRegressionModule",
    "check_compatible",
    "checkpoint_group",
    "checkpoint_shapes",
    "load_checkpoint",
    "module_from_checkpoint",
    "read_checkpoint",
    "symmetric_rotation_loss",
]
