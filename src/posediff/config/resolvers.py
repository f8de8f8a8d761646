"""Hydra/OmegaConf glue: the resolvers posediff's configs use, registered once per process.

* ``${posediff.tangent_dim:${group._target_}}`` — the tangent dimension of a group class (3 for
  SO3, 6 for SE3), so the denoiser's input/output sizes follow the chosen group.
* ``${posediff.not:${trainer.enable_progress_bar}}`` — boolean negation.
* ``${posediff.has_translation:${group._target_}}`` — whether the group's poses carry a translation.
* ``${posediff.pose_input_dim:${group._target_},${module.pose_input}}`` — the width of what the
  denoiser sees of a noisy pose (:func:`posediff.nn.pose_input_dim`).
* ``${posediff.fast_precision:${trainer.accelerator}}`` — ``bf16-mixed`` where the accelerator
  computes bf16 natively, else ``32-true`` (:func:`posediff.hardware.fast_precision`).
* ``${posediff.run_id:}`` — a random token, new for every command (:func:`new_run_id`), so that two
  runs started in the same second get their own folders (``outputs/fit/<time>_<token>``).
"""

import secrets

from hydra.utils import get_class
from omegaconf import OmegaConf

from ..nn.pose_input import pose_input_dim

_RUN_ID = [secrets.token_hex(3)]


def new_run_id() -> str:
    """A new token for ``${posediff.run_id:}`` (the command line draws one per command)."""
    _RUN_ID[0] = secrets.token_hex(3)
    return _RUN_ID[0]


def _tangent_dim(target: str) -> int:
    return int(get_class(target).dim)


def _has_translation(target: str) -> bool:
    return int(get_class(target).matrix_dim) == 4


def _fast_precision(accelerator: str = "auto") -> str:
    from ..hardware import fast_precision

    return fast_precision(str(accelerator))


def _pose_input_dim(target: str, pose_input: str) -> int:
    return pose_input_dim(get_class(target), pose_input)


def register_resolvers() -> None:
    """Register posediff's OmegaConf resolvers (idempotent)."""
    if not OmegaConf.has_resolver("posediff.tangent_dim"):
        OmegaConf.register_new_resolver("posediff.tangent_dim", _tangent_dim)
    if not OmegaConf.has_resolver("posediff.not"):
        OmegaConf.register_new_resolver("posediff.not", lambda x: not bool(x))
    if not OmegaConf.has_resolver("posediff.has_translation"):
        OmegaConf.register_new_resolver("posediff.has_translation", _has_translation)
    if not OmegaConf.has_resolver("posediff.run_id"):
        OmegaConf.register_new_resolver("posediff.run_id", lambda: _RUN_ID[0])
    if not OmegaConf.has_resolver("posediff.fast_precision"):
        OmegaConf.register_new_resolver("posediff.fast_precision", _fast_precision)
    if not OmegaConf.has_resolver("posediff.pose_input_dim"):
        OmegaConf.register_new_resolver("posediff.pose_input_dim", _pose_input_dim)


__all__ = ["new_run_id", "register_resolvers"]
