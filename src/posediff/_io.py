"""Safe output: atomic file writes (a temporary name in the same folder, then rename — no half-written
files), and output folders that posediff replaces or deletes only when it made them itself (a
:data:`MARKER` file inside; ``.``, ``..``, ``/``, the home and working folders are always refused)
and only when everything in them is what posediff wrote there (the marker lists it): a file a user
put into such a folder makes posediff refuse, never delete it."""

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (parents created; usual permissions, not mkstemp's 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise named_os_error(e, path) from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def named_os_error(e: OSError, path: str | os.PathLike[str]) -> OSError:
    """``e`` itself if it names a file, else the same error naming ``path`` (a write's ``OSError``
    names no file: a full disk would be reported without saying what could not be written)."""
    if e.filename is not None or e.errno is None:
        return e
    return OSError(e.errno, e.strerror, str(path))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (parents created)."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], data: Any) -> Path:
    """``json.dump`` ``data`` (indented, NaN allowed) to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


# --------------------------------------------------------------------------------------------------
# Output folders: posediff deletes or replaces only what it made itself
# --------------------------------------------------------------------------------------------------

#: The file posediff puts in every folder it makes and may later replace (``demo``, ``data make-bop``).
MARKER = ".posediff-output"


class OutputFolderError(ValueError):
    """An output folder posediff must not write, replace or delete (one-line message)."""


def _protected(path: Path) -> str | None:
    """Why ``path`` (resolved) may never be an output folder that gets replaced, or ``None``."""
    here, home = Path.cwd().resolve(), Path.home().resolve()
    if path == Path(path.anchor):
        return "the file-system root"
    if path == home or home.is_relative_to(path):
        return "your home folder" if path == home else "a folder that holds your home folder"
    if path == here or here.is_relative_to(path):
        return "the working folder" if path == here else "a folder that holds the working folder"
    return None


def _listing(p: Path) -> set[str]:
    """Every file and folder under ``p``, relative, the marker excepted."""
    return {str(q.relative_to(p)) for q in p.rglob("*")} - {MARKER}


def recorded_files(path: str | os.PathLike[str]) -> set[str] | None:
    """What posediff wrote into ``path`` (its marker's ``files``); ``None`` without a readable list
    (no marker, or one written before posediff recorded its files)."""
    try:
        info = json.loads((Path(path) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    files = info.get("files") if isinstance(info, dict) else None
    return {str(f) for f in files} if isinstance(files, list) else None


def foreign_files(path: str | os.PathLike[str]) -> list[str]:
    """The files and folders in ``path`` that posediff did not write there (sorted; empty when all are
    its own). Without a file list in the marker, everything but the marker counts as foreign."""
    p = Path(path)
    return sorted(_listing(p) - (recorded_files(p) or set()))


def _refuse_foreign(p: Path, key: str) -> None:
    extra = foreign_files(p)
    if extra:
        shown = ", ".join(extra[:3]) + (f" and {len(extra) - 3} more" if len(extra) > 3 else "")
        why = (
            "not written by posediff"
            if recorded_files(p) is not None
            else "not recorded by the posediff that made it"
        )
        raise OutputFolderError(
            f"{key}={p} holds files {why} ({shown}); nothing was deleted — move them out of it, or choose a new {key}="
        )


def check_output_dir(
    path: str | os.PathLike[str], command: str, *, replace: bool = True, key: str = "out"
) -> Path:
    """Refuse (:class:`OutputFolderError`, one line) an output folder ``command`` cannot safely use:
    a path under a file, an existing file, a folder that cannot be written, and — when the run will
    ``replace`` it — ``.``, ``..``, ``/``, the home or working folder (or one holding them), any
    existing, non-empty folder without posediff's :data:`MARKER` (something posediff did not make),
    and one that holds a file posediff did not write there (:func:`foreign_files`)."""
    p = Path(path).expanduser()
    resolved = p.resolve()
    why = _protected(resolved) if replace else None
    if why is not None:
        raise OutputFolderError(f"{key}={path} is {why}; give a new folder for the outputs")
    if p.exists() and not p.is_dir():
        raise OutputFolderError(f"{key}={path} is a file, not a folder; give a folder path")
    parent = resolved
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputFolderError(f"{key}={path} lies under {parent}, which is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFolderError(f"cannot write in {parent} (permission denied); choose another out=")
    if replace and p.is_dir() and any(p.iterdir()):
        if not (p / MARKER).is_file():
            raise OutputFolderError(
                f"{key}={path} exists and was not made by posediff (no {MARKER} in it); "
                "it is left alone — choose a new out= or move that folder yourself"
            )
        _refuse_foreign(p, key)
    return p


def make_output_dir(path: str | os.PathLike[str], command: str) -> Path:
    """Create ``path`` (parents too) and put posediff's :data:`MARKER` in it (with an empty file list;
    :func:`seal_output_dir` records what was written once the run is done)."""
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    atomic_write_json(p / MARKER, {"made_by": command, "files": []})
    return p


def seal_output_dir(path: str | os.PathLike[str], command: str) -> Path:
    """Record in the marker everything now in ``path`` — what ``command`` wrote into the folder it
    made — so that a later ``overwrite`` can tell its files from anyone else's."""
    p = Path(path)
    atomic_write_json(p / MARKER, {"made_by": command, "files": sorted(_listing(p))})
    return p


def remove_own_dir(path: str | os.PathLike[str], command: str) -> None:
    """Delete ``path`` if posediff made it (it holds :data:`MARKER`) and holds nothing else (no
    :func:`foreign_files`), or it is an empty folder; refuse (:class:`OutputFolderError`) anything
    else. A missing ``path`` is fine. (A ``.partial`` folder a run is writing records its files only
    at the end: while it is the run's own, everything in it counts as written by the run.)"""
    import shutil

    p = Path(path)
    if not p.exists():
        return
    if not p.is_dir():
        raise OutputFolderError(f"{p} is a file where posediff puts a folder; move it away")
    if (p / MARKER).is_file() and _protected(p.resolve()) is None:
        if recorded_files(p):  # a finished (sealed) folder: only posediff's own files in it
            _refuse_foreign(p, "out")
        shutil.rmtree(p)
    elif not any(p.iterdir()):
        p.rmdir()
    else:
        raise OutputFolderError(
            f"{p} exists and was not made by posediff (no {MARKER} in it); "
            "it is left alone — choose a new out= or move that folder yourself"
        )


def replace_dir(partial: str | os.PathLike[str], out: str | os.PathLike[str], command: str) -> Path:
    """Record what the finished ``partial`` folder holds (:func:`seal_output_dir`) and rename it to
    ``out``; an existing ``out`` must be posediff's own and hold only its files (checked first, moved
    aside, deleted only once the new one is in place)."""
    partial, out = Path(partial), Path(out)
    check_output_dir(out, command)
    seal_output_dir(partial, command)
    aside = None
    if out.exists():
        aside = out.with_name(f".{out.name}.replaced-{os.getpid()}")
        out.rename(aside)
    partial.rename(out)
    if aside is not None:
        import shutil

        if (aside / MARKER).is_file():
            shutil.rmtree(aside)
        else:  # an empty folder
            aside.rmdir()
    return out
