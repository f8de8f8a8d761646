"""``posediff.lie``: batched Lie groups in torch (SO3, R3SO3, SE3, SE2) and their registry.

Elements are matrices, tangents are ``[ρ, φ]`` (translation first), perturbations act on the
right: ``Y = X · Exp(z)``. See :mod:`posediff.lie.base` and ``docs/conventions.md``.
"""

from typing import Any

from .._registry import UnknownNameError as UnknownNameError
from .base import LieGroup as LieGroup
from .r3so3 import R3SO3 as R3SO3
from .se2 import SE2 as SE2
from .se3 import SE3 as SE3
from .so3 import SO3 as SO3


def get_group(name: str, **kwargs: Any) -> LieGroup:
    """An instance of the registered group ``name`` (``"so3"``, ``"r3so3"``, ``"se3"``, ``"se2"``, ...).

    An unknown name raises :class:`UnknownNameError` (a ``KeyError``) listing the registered names.
    """
    cls: type[LieGroup] = LieGroup.lookup(name)
    return cls(**kwargs)


def registered_groups() -> dict[str, type[LieGroup]]:
    """A snapshot of the group registry: name → class."""
    return dict(LieGroup.registry)


__all__ = ["LieGroup", "SO3", "R3SO3", "SE3", "SE2", "get_group", "registered_groups", "UnknownNameError"]
