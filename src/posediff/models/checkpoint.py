"""Checkpoints: a trained model from one file, without the config files it was trained with.

``posediff fit`` stores the resolved run configuration in every Lightning checkpoint (key
``posediff_config``). :func:`load_checkpoint` reads the file with ``torch.load(weights_only=True)``
(tensors and plain containers only — no pickled code runs), checks the stored config against
posediff's allow-list (:mod:`posediff.config.allowlist`: only posediff's own classes, no interpolations —
a tampered file is refused in one line before anything in it is imported, resolved or called),
rebuilds the module from it with Hydra's ``instantiate`` and loads the weights. With the authors' EMA on
(``ema=authors``), Lightning's ``EMAWeightAveraging`` puts the averaged weights in ``state_dict``,
so evaluation uses the EMA weights.

A checkpoint is refused with one line when it was trained for another group or shape set than the
caller asks for (:func:`check_compatible`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from ..config.allowlist import UntrustedConfigError, check_config, target_class, upgrade_config
from ..lie import LieGroup
from ..options import OptionError, check_options

CONFIG_KEY = "posediff_config"

#: checkpoint keys beside Lightning's: the run configuration, the diffusion's description, the training
#: loss so far (float64 tensor) and the global RNG states (exact resume)
DIFFUSION_KEY = "posediff_diffusion"
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


class CheckpointError(ValueError):
    """A checkpoint that cannot serve the request (missing, not posediff's, or trained differently)."""


def read_checkpoint(path: str | os.PathLike[str], map_location: Any = "cpu") -> dict[str, Any]:
    """The checkpoint dict (``weights_only=True``, memory-mapped, so reading only its config costs
    nothing); one-line errors for a missing or foreign file."""
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"checkpoint {p} not found (posediff fit writes them to <run>/checkpoints/)")
    import zipfile

    if not zipfile.is_zipfile(p):
        raise CheckpointError(
            f"{p} is not a PyTorch checkpoint (not the zip archive torch.save writes; truncated or another "
            "kind of file?); give a .ckpt written by posediff fit"
        )
    try:
        ckpt = torch.load(p, map_location=map_location, weights_only=True, mmap=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file gets the same one-line message
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"cannot read checkpoint {p}: {first}") from e
    if not isinstance(ckpt, dict) or CONFIG_KEY not in ckpt or "state_dict" not in ckpt:
        raise CheckpointError(
            f"{p} is not a posediff checkpoint (no stored run config; made by posediff fit?)"
        )
    try:
        check_config(ckpt[CONFIG_KEY], where=f"checkpoint {p}")
    except UntrustedConfigError as e:
        raise CheckpointError(str(e)) from None
    ckpt[CONFIG_KEY] = upgrade_config(ckpt[CONFIG_KEY])  # classes that moved: their new dotted names

    try:  # sizes from a file are checked before anything is built (a million levels, 2e6-wide layers …)
        check_options(ckpt[CONFIG_KEY], where=f"checkpoint {p}")
    except OptionError as e:
        raise CheckpointError(str(e)) from None
    return ckpt


def check_finite_state(state: dict[str, Any], where: str) -> None:
    """Refuse (one line) a state dict with a NaN or infinite weight: sampling with it gives NaN poses
    (and NaN crop boxes crash torchvision's ``roi_align``); the first such tensor is named."""
    for key, value in state.items():
        if (
            isinstance(value, torch.Tensor)
            and value.is_floating_point()
            and not bool(torch.isfinite(value).all())
        ):
            bad = int((~torch.isfinite(value)).sum())
            raise CheckpointError(
                f"{where}: weight {key} holds {bad} NaN/infinite value(s) (a diverged or damaged run); "
                "use an earlier checkpoint of the run (best.ckpt, or retrain with a lower module.lr)"
            )


def checkpoint_group(config: dict[str, Any]) -> str:
    """The group name a stored config trains on (from ``group._target_``, an allowed class; no
    module is imported on a file's word)."""
    try:
        cls = target_class(config.get("group") or {}, where="stored config group")
    except UntrustedConfigError as e:
        raise CheckpointError(str(e)) from None
    if not (isinstance(cls, type) and issubclass(cls, LieGroup)):
        raise CheckpointError(f"stored config: group._target_ names {cls.__name__}, not a LieGroup")
    return str(cls.name)


def checkpoint_shapes(config: dict[str, Any]) -> list[str]:
    return [str(s) for s in (config.get("data") or {}).get("shapes", [])]


def check_compatible(
    config: dict[str, Any],
    *,
    group: str | None = None,
    shapes: Sequence[str] | None = None,
    where: str = "checkpoint",
) -> None:
    """Raise :class:`CheckpointError` when ``config`` was trained on another group or on fewer shapes."""
    have = checkpoint_group(config)
    if group is not None and group != have:
        raise CheckpointError(
            f"{where} was trained on group {have!r}, not {group!r}; use a {group} checkpoint or group={have}"
        )
    if shapes is not None:
        trained = checkpoint_shapes(config)
        missing = [s for s in shapes if s not in trained]
        if missing:
            raise CheckpointError(
                f"{where} was trained on the shapes {trained}; it cannot evaluate {missing} "
                f"(set data.shapes to a subset of {trained})"
            )


def module_from_checkpoint(
    ckpt: dict[str, Any], path: str | os.PathLike[str] = "checkpoint", *, expected: type
):  # noqa: ANN201
    """The module of a checkpoint dict already read with :func:`read_checkpoint`, in eval mode, with
    ``module.config`` set to the stored run config; refused (one line) unless its class is a subclass
    of ``expected`` (the caller's base class: ``posediff.models.PoseModule`` for any pose model)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    config = upgrade_config(ckpt[CONFIG_KEY])
    try:  # again here: a caller may hand in a dict it did not get from read_checkpoint
        check_config(config, where=f"checkpoint {path}")
        cls = target_class(config.get("module") or {}, where=f"checkpoint {path}: module")
    except UntrustedConfigError as e:
        raise CheckpointError(str(e)) from None
    if not (isinstance(cls, type) and issubclass(cls, expected)):
        raise CheckpointError(f"{path}: its module config names {cls.__name__}, not a {expected.__name__}")
    module_cfg = OmegaConf.create(config["module"])
    if module_cfg.get("encoder") is not None and "weights" in module_cfg.encoder:
        module_cfg.encoder.weights = None  # the checkpoint holds the trained weights; no file needed
    module = instantiate(module_cfg)
    if not isinstance(module, expected):
        raise CheckpointError(f"{path}: its module config builds {type(module).__name__}")
    check_finite_state(ckpt["state_dict"], f"checkpoint {path}")
    try:
        module.load_state_dict(ckpt["state_dict"])
    except RuntimeError as e:  # a tensor of another shape, or keys of another architecture
        lines = [ln.strip() for ln in str(e).splitlines()[1:] if ln.strip()]
        detail = lines[0] if lines else str(e).splitlines()[0]
        raise CheckpointError(
            f"checkpoint {path}: its weights do not fit the architecture its config describes ({detail}); "
            "the file is damaged or was edited"
        ) from None
    module.config = config
    module.eval()
    return module


def load_checkpoint(
    path: str | os.PathLike[str],
    *,
    expected: type,
    map_location: Any = "cpu",
    group: str | None = None,
    shapes: Sequence[str] | None = None,
):  # noqa: ANN201 - PoseDiffusionModule (imported lazily)
    """The trained module (a subclass of ``expected``) of a ``posediff fit`` checkpoint, in eval mode
    (``posediff.load_checkpoint`` is this with ``expected=PoseModule``).

    ``group`` / ``shapes``: refuse (one line) a checkpoint trained on another group or without
    those shapes. ``module.config`` holds the stored run configuration.
    """
    ckpt = read_checkpoint(path, map_location)
    check_compatible(ckpt[CONFIG_KEY], group=group, shapes=shapes, where=f"checkpoint {path}")
    return module_from_checkpoint(ckpt, path, expected=expected)


__all__ = [
    "CONFIG_KEY",
    "DIFFUSION_KEY",
    "LOSS_HISTORY_KEY",
    "RNG_KEY",
    "CheckpointError",
    "check_compatible",
    "check_finite_state",
    "checkpoint_group",
    "checkpoint_shapes",
    "load_checkpoint",
    "module_from_checkpoint",
    "read_checkpoint",
    "rng_state",
    "set_rng_state",
]
