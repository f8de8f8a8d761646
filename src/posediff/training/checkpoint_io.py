"""Checkpoint files that survive a kill and a full disk: posediff's Lightning ``CheckpointIO``.

Lightning's ``TorchCheckpointIO`` saves a local checkpoint through an fsspec transaction: the bytes go
to ``tempfile.mkstemp()`` — a file in ``$TMPDIR`` — and the commit is ``shutil.move`` onto the final
name. When ``$TMPDIR`` is another filesystem than the run folder (a tmpfs ``/tmp``, outputs on a disk
or NFS) the move is a copy that first truncates ``last.ckpt``: a kill during the copy leaves a
fragment under the final name (the only checkpoint of the run), a full disk leaves a fragment and a
traceback, and every kill leaves the whole temporary copy behind in ``$TMPDIR``.

:class:`AtomicCheckpointIO` (in ``conf/trainer/default.yaml``'s ``plugins:``, so ``posediff fit`` always
uses it) writes a local checkpoint to a temporary name in the destination folder
(``.last.ckpt.posediff-<host>-<pid>.tmp``), flushes and fsyncs it, ``os.replace``\\ s it onto the final
name and fsyncs the folder. Nothing is copied and ``$TMPDIR`` is never used, so at any moment the final
name holds either the previous checkpoint or the new one, whole. A failed save (``ENOSPC``, a
permission, an I/O error) removes its temporary file and raises :class:`CheckpointWriteError`, one
line naming the file, the cause and what to do. Temporary files of that pattern left by killed
processes are removed before each save and when a run resumes from a checkpoint in that folder
(:func:`remove_stale_temp_files`); nothing else is ever deleted. Remote paths (``s3://`` …) go to
Lightning's own implementation unchanged.
"""

from __future__ import annotations

import errno
import io
import logging
import os
import re
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import torch
from lightning.fabric.utilities.types import _PATH
from lightning.pytorch.plugins.io import TorchCheckpointIO

log = logging.getLogger(__name__)

#: posediff's temporary checkpoint names: ``.<final name>.posediff-<host>-<pid>.tmp`` in the final folder.
TEMP_PATTERN = re.compile(r"^\.(?P<name>.+)\.posediff-(?P<host>[A-Za-z0-9_-]+)-(?P<pid>[0-9]+)\.tmp$")

#: A temporary file of another host (or of a live process id here) untouched this long is a leftover:
#: a writer appends to it continuously and renames it within seconds of its last write.
STALE_AFTER_S = 3600.0


class CheckpointWriteError(OSError):
    """A checkpoint that could not be written (one-line message: the file, the cause, what to do). The
    file under the final name, if any, is the previous checkpoint, whole; no temporary file is left."""

    def __init__(self, message: str, *, path: Any = None, code: int | None = None, cause: str | None = None):
        super().__init__(message)
        self.message = message
        self.errno = code
        self.strerror = cause
        self.filename = None if path is None else str(path)

    def __str__(self) -> str:  # OSError's own would be "[Errno 28] ...: 'path'"
        return self.message


def _host() -> str:
    name = socket.gethostname().split(".", 1)[0]
    return re.sub(r"[^A-Za-z0-9-]", "_", name)[:40] or "host"


def temp_path(path: str | os.PathLike[str]) -> Path:
    """The temporary name this process writes ``path`` under (same folder, matches :data:`TEMP_PATTERN`)."""
    p = Path(path)
    return p.with_name(f".{p.name}.posediff-{_host()}-{os.getpid()}.tmp")


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except OSError:
        return True  # cannot tell: keep the file
    return True


def _is_stale(entry: os.DirEntry[str], match: re.Match[str], host: str, now: float) -> bool:
    try:
        age = now - entry.stat(follow_symlinks=False).st_mtime
    except OSError:
        return False
    if age > STALE_AFTER_S:
        return True
    if match["host"] != host:  # another machine's process id says nothing here
        return False
    pid = int(match["pid"])
    return pid != os.getpid() and not _pid_alive(pid)


def remove_stale_temp_files(folder: str | os.PathLike[str]) -> list[Path]:
    """Delete posediff's temporary checkpoint files in ``folder`` whose writer is gone: this host's
    process id is not running, or (any host) untouched for :data:`STALE_AFTER_S`. Only regular files
    matching :data:`TEMP_PATTERN` are considered; errors are ignored (best effort). Returns the
    removed paths."""
    removed: list[Path] = []
    host, now = _host(), time.time()
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = TEMP_PATTERN.match(entry.name)
        if match is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False) or not _is_stale(entry, match, host, now):
                continue
            os.unlink(entry.path)
        except OSError:
            continue
        removed.append(Path(entry.path))
        log.info("removed %s (a temporary checkpoint file left by a killed process)", entry.path)
    return removed


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (skipped where the filesystem cannot fsync a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_ADVICE = {
    errno.ENOSPC: "free space on that disk or set hydra.run.dir to a folder on another one",
    getattr(errno, "EDQUOT", -1): "free space within your quota or set hydra.run.dir to a folder elsewhere",
    errno.EACCES: "make that folder writable or set hydra.run.dir to another folder",
    errno.EPERM: "make that folder writable or set hydra.run.dir to another folder",
    errno.EROFS: "set hydra.run.dir to a folder on a writable filesystem",
}


def _write_error(path: Path, e: OSError, tmp: Path) -> CheckpointWriteError:
    path = Path(os.path.abspath(path))
    text = (e.strerror or str(e) or type(e).__name__).strip().splitlines()
    cause = text[0] if text else type(e).__name__
    cause = cause[:1].lower() + cause[1:]
    try:
        before = path.is_file()
        last = path.with_name("last.ckpt")
        resume = last if last.is_file() else (path if before else None)
    except OSError:
        before, resume = False, None
    kept = f"the previous {path.name} is unchanged" if before else f"no earlier {path.name} existed"
    kept += f"; remove {tmp} yourself" if os.path.lexists(tmp) else "; no partial file was left"
    advice = _ADVICE.get(e.errno or 0, "check that folder and its disk")
    then = f", then resume with ckpt_path={resume}" if resume is not None else ""
    return CheckpointWriteError(
        f"cannot save checkpoint {path}: {cause} ({kept}); {advice}{then}",
        path=path,
        code=e.errno,
        cause=cause,
    )


def write_atomically(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object]) -> Path:
    """Write a file through ``write(f)`` so that ``path`` is always either its previous content or the
    new one, whole: a temporary name in ``path``'s folder (:func:`temp_path`), flushed and fsynced, then
    ``os.replace``\\ d onto ``path`` (the folder fsynced too). Stale temporary files of killed writers in
    that folder are removed first. Any exception removes the temporary file; an ``OSError`` becomes a
    one-line :class:`CheckpointWriteError`, anything else (a bug, Ctrl-C) propagates unchanged."""
    path = Path(path)
    folder = path.parent
    tmp = temp_path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale_temp_files(folder)
        flags = (
            os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
        )
        fd = os.open(tmp, flags, 0o666)  # the usual permissions (umask applies), not mkstemp's 0600
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError) and not isinstance(e, CheckpointWriteError):
            raise _write_error(path, e, tmp) from e
        raise
    _fsync_dir(folder)
    return path


def save_torch(obj: Any, path: str | os.PathLike[str]) -> Path:
    """``torch.save(obj)`` to ``path`` through :func:`write_atomically`. Serialised in memory first, as
    Lightning does: a failing ``torch.save`` touches no file, and a write error stays an ``OSError``
    (streamed into the file, torch's zip writer turns an ``ENOSPC`` into a ``RuntimeError``)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    return write_atomically(path, lambda f: f.write(buf.getbuffer()))


def _local(path: _PATH) -> Path | None:
    """``path`` as a local path, or ``None`` for a remote URL (``s3://`` …)."""
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if text.startswith("file://"):
        return Path(text[len("file://") :])
    if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*://", text):
        return None
    return Path(text)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's ``TorchCheckpointIO``, with local saves that a kill or a full disk cannot corrupt
    (see the module docstring): same file format, loading and remote-path behaviour.

    Use it through the trainer config (``conf/trainer/default.yaml``)::

        plugins:
          - _target_: posediff.training.checkpoint_io.AtomicCheckpointIO
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: _PATH, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None:
            raise TypeError(
                "`Trainer.save_checkpoint(..., storage_options=...)` with `storage_options` arg is not supported "
                f"for `{type(self).__name__}`"
            )
        local = _local(path)
        if local is None:
            super().save_checkpoint(checkpoint, path)
            return
        save_torch(checkpoint, local)

    def load_checkpoint(self, path: _PATH, *args: Any, **kwargs: Any) -> dict[str, Any]:
        local = _local(path)
        if local is not None:  # a resume: leftovers of the killed run next to its checkpoint go
            remove_stale_temp_files(local.parent)
        return super().load_checkpoint(path, *args, **kwargs)

    def remove_checkpoint(self, path: _PATH) -> None:
        """Delete a local checkpoint file (``os.unlink``, the folder fsynced; one already gone is fine). A
        folder at the path (a sharded checkpoint) and remote paths go to Lightning's method, as before."""
        local = _local(path)
        if local is None or (local.is_dir() and not local.is_symlink()):
            super().remove_checkpoint(path)
            return
        try:
            local.unlink()
        except FileNotFoundError:
            return
        _fsync_dir(local.parent)
        log.debug("removed checkpoint %s", local)


__all__ = [
    "AtomicCheckpointIO",
    "CheckpointWriteError",
    "STALE_AFTER_S",
    "TEMP_PATTERN",
    "remove_stale_temp_files",
    "save_torch",
    "temp_path",
    "write_atomically",
]
