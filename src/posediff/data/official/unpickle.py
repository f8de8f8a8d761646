"""Plain data out of a (gzipped) pickle, never code: :func:`load_plain_pickle`.

Unpickling runs whatever callable the file names (``GLOBAL`` / ``STACK_GLOBAL`` / ``INST`` / ``OBJ`` /
the extension registry all resolve names through :meth:`pickle.Unpickler.find_class`, and ``REDUCE``
calls what they resolved). :class:`PlainUnpickler` refuses every name, and persistent ids, so a file
yields only what the pickle opcodes build by themselves — ``dict``, ``list``, ``tuple``, ``set``,
``str``, ``bytes``, ``int``, ``float``, ``bool``, ``None`` — or is refused in one line before any
callable is looked up, let alone run. The authors' SYMSOL-T ``annotations.gz`` is such a file
(a list of plain dicts).
"""

from __future__ import annotations

import gzip
import io
import os
import pickle
import zlib
from pathlib import Path
from typing import Any


class UnsafePickleError(ValueError):
    """A pickle that names a class or function (refused; nothing was run)."""


class PlainUnpickler(pickle.Unpickler):
    """An unpickler that resolves no name at all (module docstring)."""

    def find_class(self, module: str, name: str) -> Any:  # noqa: D102
        raise UnsafePickleError(f"{module}.{name}")

    def persistent_load(self, pid: Any) -> Any:  # noqa: D102
        raise UnsafePickleError("a persistent id")


def load_plain_pickle(path: str | os.PathLike[str], *, compressed: bool | None = None) -> Any:
    """The plain data in the pickle at ``path`` (gzipped when ``compressed``; ``None``: when the file
    starts with gzip's magic bytes or its name ends in ``.gz``). Every failure is one line naming the
    file: not gzip, truncated, not a pickle, or a pickle that names a class or function."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise UnsafePickleError(f"{path}: cannot read ({e.strerror or e})") from None
    gz = raw[:2] == b"\x1f\x8b"
    if compressed is None:
        compressed = gz or path.suffix == ".gz"
    if compressed:
        if not gz:
            raise UnsafePickleError(f"{path}: not a gzip file (expected the authors' gzipped pickle)")
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as e:
            raise UnsafePickleError(f"{path}: damaged or truncated gzip data ({e})") from None
    try:
        return PlainUnpickler(io.BytesIO(raw)).load()
    except UnsafePickleError as e:
        raise UnsafePickleError(
            f"{path}: refused — the pickle names {e} (posediff reads only plain lists, dicts, numbers "
            "and strings from it; nothing in it was run)"
        ) from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError, KeyError, MemoryError) as e:
        raise UnsafePickleError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from None


__all__ = ["PlainUnpickler", "UnsafePickleError", "load_plain_pickle"]
