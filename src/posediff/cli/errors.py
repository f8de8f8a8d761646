"""The one place where an error a user caused becomes one line.

``posediff <command>`` prints ``posediff <command>: <one line>`` and exits 2 for every error that
:func:`one_line` recognises (:func:`reports_input_errors`, the decorator every command's ``run`` gets);
anything else is a bug and keeps its traceback. Recognised are:

* posediff's own input errors — any ``ValueError`` / ``OSError`` subclass defined in a posediff
  module (checkpoints, data, options, outputs), also when Hydra, Lightning or a DataLoader worker
  wrapped it (the exception chain is followed);
* a full or read-only disk, a quota, a lost network file system (``OSError`` with ``ENOSPC``,
  ``EDQUOT``, ``EROFS``, ``EIO``) anywhere in the chain — every file posediff writes goes to a
  temporary name in its folder first, so nothing half-written is left under a final name;
* Hydra's own command-line errors (:func:`hydra_line`): an unknown key (with the closest known
  ones), a config group given twice, an override its grammar cannot parse (with how to quote it).

Where a command builds what the user described (data, a module, a checkpoint's run), errors of the
libraries it calls are the user's too (a ``ValueError`` from a data module wrapped by Hydra's
``instantiate``): :func:`user_input` marks such a stretch, and turns them into :class:`InputError`.
"""

from __future__ import annotations

import difflib
import errno
import functools
import re
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

#: ``errno`` values that mean "the disk cannot take the file", not a bug.
DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG}


class InputError(ValueError):
    """An input the user can fix; its message is the one line ``posediff <command>`` prints."""


def chain(e: BaseException | None, *, context: bool = True, limit: int = 12) -> Iterator[BaseException]:
    """``e`` and the exceptions behind it: each one's ``__cause__`` (``raise ... from``), or with
    ``context`` also its ``__context__`` (raised while handling another)."""
    seen: set[int] = set()
    while e is not None and id(e) not in seen and len(seen) < limit:
        seen.add(id(e))
        yield e
        e = e.__cause__ or (e.__context__ if context else None)


def first_line(e: BaseException) -> str:
    """The first non-empty line of ``str(e)`` (the class name when empty)."""
    for line in str(e).strip().splitlines():
        if line.strip():
            return line.strip()
    return type(e).__name__


def _posediff_line(e: BaseException) -> str:
    lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
    if not lines:
        return type(e).__name__
    if lines[0].startswith("Caught ") and len(lines) > 1:  # re-raised from a DataLoader worker
        last = lines[-1]
        name = type(e).__name__
        return last.split(": ", 1)[1] if last.startswith(name + ":") else last
    return lines[0]


def stdout_is_device() -> bool:
    """Standard output is a device that is not a terminal (``> /dev/full``)."""
    import os
    import stat
    import sys

    try:
        return stat.S_ISCHR(os.fstat(sys.stdout.fileno()).st_mode) and not sys.stdout.isatty()
    except (OSError, ValueError, AttributeError):
        return False


def disk_line(e: OSError) -> str:
    """``no space left on device writing FILE; free space or ...`` for a disk-full style ``OSError``
    (``cannot write to standard output`` when no file is named and stdout is a device: ``> /dev/full``)."""
    if e.filename is None and stdout_is_device():
        return f"cannot write to standard output ({e.strerror}); redirect it to a file or folder with room"
    what = {
        errno.ENOSPC: "no space left on device",
        errno.EDQUOT: "disk quota exceeded",
        errno.EROFS: "read-only file system",
        errno.EIO: "input/output error",
        errno.EFBIG: "file too large for the file system",
    }.get(e.errno or 0, e.strerror or "cannot write")
    where = f" writing {e.filename}" if e.filename else ""
    return (
        f"{what}{where}; nothing half-written was left under a final name — free space (or choose "
        "another out= / hydra.run.dir=) and run again"
    )


def one_line(e: BaseException) -> str | None:
    """The one line for an error the user can fix (module docstring), else ``None`` (a bug)."""
    for err in chain(e):
        cls = type(err)
        if cls.__module__.startswith("posediff") and issubclass(cls, (ValueError, OSError)):
            return _posediff_line(err)
    for err in chain(e):
        if isinstance(err, OSError) and err.errno in DISK_ERRNOS:
            return disk_line(err)
        if isinstance(err, RuntimeError) and re.search(
            r"file write failed|No space left|PytorchStreamWriter failed", str(err)
        ):
            return disk_line(OSError(errno.ENOSPC, "no space left on device"))
    return None


@contextmanager
def user_input(*types: type[BaseException]) -> Iterator[None]:
    """A stretch of a command that builds what the user described: an exception of ``types`` (default
    ``ValueError``, ``FileNotFoundError``) raised inside — itself, or behind the wrappers of Hydra's
    ``instantiate`` (its ``__cause__`` chain) — becomes an :class:`InputError` with its one line."""
    types = types or (ValueError, FileNotFoundError)
    try:
        yield
    except InputError:
        raise
    except Exception as e:
        err = next((x for x in chain(e, context=False) if isinstance(x, types)), None)
        if err is None:
            raise
        raise InputError(_posediff_line(err)) from e


def record_failure(name: str, code: int, message: str | None) -> None:
    """In a multirun, a failed job leaves ``failed.json`` in its folder for ``posediff report``."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        from .._io import atomic_write_json

        hc = HydraConfig.get()
        if hc.mode != RunMode.MULTIRUN:
            return
        atomic_write_json(
            Path(hc.runtime.output_dir) / "failed.json",
            {"command": name, "exit_code": code, "message": message, "overrides": list(hc.overrides.task)},
        )
    except Exception:  # noqa: BLE001 - the record is a courtesy; the exit code already says it
        pass


def fail(prefix: str, message: str, code: int = 2) -> int:
    """Print ``prefix: message`` on stderr; the exit code."""
    print(f"{prefix}: {message}", file=sys.stderr)
    return code


def reports_input_errors(name: str) -> Callable[[Callable[..., int | None]], Callable[..., int]]:
    """The decorator of every command's ``run(cfg) -> int``: an input error (:func:`one_line`: posediff's
    own, a full disk, also behind Hydra's and DataLoader workers' wrappers) or a required key left
    empty becomes ``posediff <name>: <one line>`` on stderr and exit code 2; in a multirun the job's
    failure is recorded (:func:`record_failure`). Anything else propagates with its traceback."""
    prefix = f"posediff {name}"

    def wrap(run: Callable[..., int | None]) -> Callable[..., int]:
        @functools.wraps(run)
        def guarded(cfg: Any, *args: Any, **kwargs: Any) -> int:
            from omegaconf.errors import MissingMandatoryValue

            try:
                code = int(run(cfg, *args, **kwargs) or 0)
                message = None
            except MissingMandatoryValue as e:
                key = e.full_key or "a key"
                message = f"{key} is required ({key}=...; posediff {name} --help lists the options)"
                code = fail(prefix, message)
            except Exception as e:  # noqa: BLE001 - input errors become one line; others propagate
                message = one_line(e)
                if message is None:
                    raise
                code = fail(prefix, message)
            if code:
                record_failure(name, code, message)
            return code

        return guarded

    return wrap


# --------------------------------------------------------------------------------------------------
# Hydra's command-line errors
# --------------------------------------------------------------------------------------------------


def _known_keys(node: object) -> list[str]:
    try:
        return [str(k) for k in node.keys()]  # type: ignore[attr-defined]
    except Exception:  # noqa: BLE001 - no parent node to suggest from
        return []


def hydra_line(e: BaseException, args: list[str]) -> str | None:
    """One line for an error Hydra raised while composing the command line's config, else ``None``."""
    try:
        from hydra.errors import HydraException, OverrideParseException
        from omegaconf.errors import OmegaConfBaseException
    except ImportError:  # pragma: no cover
        return None
    if not isinstance(e, (HydraException, OmegaConfBaseException)):
        return None
    text = str(e)
    cause = e.__cause__
    # unknown key: "Could not override 'trainer.max_step'." ← "Key 'max_step' is not in struct"
    m = re.search(r"Could not override '([^']+)'", text)
    if m and cause is not None and "not in struct" in str(cause):
        key = m.group(1)
        parent, _, leaf = key.rpartition(".")
        known = _known_keys(getattr(cause, "parent_node", None))
        close = difflib.get_close_matches(leaf, known, n=3, cutoff=0.6)
        hint = (
            f"did you mean {' or '.join((parent + '.' if parent else '') + c for c in close)}? "
            if close
            else ""
        )
        value = next((a.split("=", 1)[1] for a in args if a.split("=", 1)[0].lstrip("+~") == key), "...")
        return f"unknown key {key}: {hint}(+{key}={value} adds a new key; --cfg job lists the keys)"
    m = re.search(r"Multiple values for (\S+?)\.", text)
    if m:
        group = m.group(1)
        given = [a for a in args if a.lstrip("+~").split("=", 1)[0] == group]
        return f"{group} is given more than once ({' '.join(given) or group}); give one {group}=..."
    m = re.search(r"Ambiguous value for argument '([^']+)'", text)
    if m:
        arg = m.group(1)
        key, _, value = arg.partition("=")
        return (
            f"{arg}: a comma makes a list or a sweep; quote it to keep it one value ({key}='{value}'), "
            f"write {key}=[{value}] for a list, or add -m to sweep"
        )
    if isinstance(e, OverrideParseException) or "override_grammar" in text:
        bad = next((a for a in args if a in text), None) or first_line(e)
        key, _, value = bad.partition("=")
        return (
            f"cannot read the override {bad!r} (Hydra's grammar reserves = , [ ] ( ) ' \" and spaces in "
            f"values): quote the value, e.g. {_quoted(key, value)}"
        )
    m = re.search(r"Could not append to config. An item is already at '([^']+)'", text)
    if m:
        return f"+{m.group(1)}=... adds a key that exists already; write {m.group(1)}=... to change it"
    line = first_line(e)
    if cause is not None and isinstance(cause, OmegaConfBaseException):
        line = f"{line} {first_line(cause)}"
    return f"{line} (posediff <command> --help lists the options)"


def _quoted(key: str, value: str) -> str:
    """``key="value"`` (Hydra's quoting) written so that a POSIX shell passes it through unchanged."""
    quote = '"' if "'" in value else "'"
    escaped = value.replace("\\", "\\\\").replace(quote, "\\" + quote)
    hydra_arg = f"{key}={quote}{escaped}{quote}"
    return "'" + hydra_arg.replace("'", "'\\''") + "'"


__all__ = ["DISK_ERRNOS", "InputError", "chain", "disk_line", "fail", "first_line", "hydra_line", "one_line",
           "record_failure", "reports_input_errors", "user_input"]  # fmt: skip
