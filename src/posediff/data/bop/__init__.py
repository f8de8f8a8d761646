"""BOP-format datasets (T-LESS and any other BOP dataset): the reader (:mod:`.reader`), region-of-interest
crops with Dynamic Zoom-In (:mod:`.roi`), the network's pose encoding (:mod:`.encoding`), kornia
augmentation (:mod:`.augment`), per-instance datasets and the Lightning data module
(:mod:`.datamodule`), a renderer for object meshes (:mod:`.render`) and the BOP-format fixture
``posediff data make-bop`` writes (:mod:`.fixture`, imported only when one of its names is asked for)."""

from typing import Any

from .augment import HardAugment
from .datamodule import BopDataModule, BopInstanceDataset, keep_instance
from .encoding import PoseEncoding, allocentric_rotation
from .reader import BopFormatError, BopModels, BopSplit, Instance, Target, read_targets, target_instances
from .render import BopRenderer, RenderedScene

_LAZY = {"BopFixtureSummary": "fixture", "make_bop_fixture": "fixture"}


def __getattr__(name: str) -> Any:  # PEP 562: the fixture generator is loaded on first use
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BopDataModule",
    "BopFixtureSummary",
    "BopRenderer",
    "RenderedScene",
    "make_bop_fixture",
    "BopFormatError",
    "BopInstanceDataset",
    "BopModels",
    "BopSplit",
    "HardAugment",
    "Instance",
    "PoseEncoding",
    "Target",
    "allocentric_rotation",
    "keep_instance",
    "read_targets",
    "target_instances",
]
