"""Registration by subclassing, for every pluggable family (groups now; kernels, samplers later).

A family root is declared with ``family=True``; each subclass that passes ``name=...`` is recorded
in the root's read-only ``registry``::

    class LieGroup(Registered, family=True): ...
    class SE3(LieGroup, name="se3"): ...
    LieGroup.registry["se3"] is SE3

The registry is *derived* from the class definitions. It is used for lookup by name, for
parametrizing contract tests and for error messages; objects are built from config by Hydra's
``_target_``, never through this registry.
"""

import re
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class Registered:
    """Mixin that records named subclasses in a per-family, read-only registry."""

    name: ClassVar[str]
    registry: ClassVar[Mapping[str, type[Any]]]
    _entries: ClassVar[dict[str, type[Any]]]

    def __init_subclass__(cls, *, name: str | None = None, family: bool = False, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if family:
            if name is not None:
                raise TypeError(f"{cls.__qualname__}: a family root cannot also take a name")
            cls._entries = {}
            cls.registry = MappingProxyType(cls._entries)
            return
        if not hasattr(cls, "_entries"):
            raise TypeError(f"{cls.__qualname__} derives from Registered but from no family root")
        if name is None:
            return  # an abstract intermediate class: not registered
        if not _NAME.match(name):
            raise ValueError(f"{cls.__qualname__}: registry name {name!r} must match {_NAME.pattern}")
        previous = cls._entries.get(name)
        if previous is not None and _qualified(previous) != _qualified(cls):
            raise TypeError(
                f"{cls.__qualname__}: the name {name!r} is already registered by {_qualified(previous)}"
            )
        cls.name = name
        # Re-defining the same class (a module reload, a re-run notebook cell) replaces the entry.
        cls._entries[name] = cls

    @classmethod
    def lookup(cls, name: str) -> type[Any]:
        """The registered class called ``name``; a ``KeyError`` lists the registered names."""
        try:
            return cls.registry[name]
        except KeyError:
            known = ", ".join(sorted(cls.registry)) or "(none)"
            raise UnknownNameError(f"unknown {_family_label(cls)} {name!r}; registered: {known}") from None


class UnknownNameError(KeyError):
    """A registry lookup of a name nobody registered; the message lists the registered names."""

    def __str__(self) -> str:  # KeyError would print the message in quotes
        return str(self.args[0]) if self.args else ""


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _family_label(cls: type) -> str:
    for klass in cls.__mro__:
        if "registry" in vars(klass):
            return str(getattr(klass, "family_label", klass.__name__))
    return cls.__name__
