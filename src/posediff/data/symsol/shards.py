"""On-disk SYMSOL / SYMSOL-T: shards that stream, an index, atomic and resumable rendering.

Layout of one split, ``<out>/<split>/``::

    meta.json             what was asked for (dataset, variant, split, seed, sizes, K, the renderer's
                          scene version and look), the
                          digest of all its poses and ``complete`` (false until the last shard is written)
    index.npz             per sample: shape_id, R (3×3), t (3, camera frame), shard, offset
    shard-00000.npz …     ``shard_size`` samples each: rgb (n, H, W, 3) uint8, depth (n, H, W) uint16
                          in units of ``depth_scale`` (0 = background; mask = depth > 0), index (n,),
                          provenance (one JSON string: the render the shard belongs to)

Provenance: every shard records what it was rendered from — dataset, variant, split, seed, shapes,
``n_per_shape``, image size, look and renderer settings (the scene version among them), shard size,
its number and index range, and the
SHA-256 of the poses it holds (:func:`~posediff.data.symsol.poses.pose_digest`). A resumed render
checks every shard already in the folder against the render asked for (also when ``meta.json`` is
gone) and refuses one that differs; :class:`SymsolShards` checks every shard against ``meta.json``
and ``index.npz`` when it opens a split and again when it loads a shard. Folders of the earlier
format (``posediff-symsol/1``, shards without provenance) cannot be checked and are refused by both;
folders of posediff's first scene (``posediff-symsol/2``: a 1.9× smaller icosahedron, other lighting,
:data:`~posediff.data.symsol.render.SCENE_VERSION`) are refused in one line naming the render command
(their images are not the paper's, so a model trained on them is not either).

``look``: ``paper`` renders every image in the authors' look; ``varied`` draws one per image
(:meth:`~posediff.data.symsol.render.Look.sample`) from a generator seeded by (seed, split, image
index), so the same seed gives the same images, whatever the shard size or the number of workers.

Every file is written to a temporary name in the same folder and renamed, so an interrupted render
leaves only whole shards; running the same command again renders only the missing ones. With
``workers`` > 1 the pool's processes ignore SIGINT: on Ctrl-C the parent terminates them, removes
their temporary files and raises ``KeyboardInterrupt`` (one traceback, not one per process). In one
process a Ctrl-C is taken between two images, never inside the renderer: a ``KeyboardInterrupt``
raised inside pyrender, trimesh or networkx can be swallowed there (trimesh catches ``BaseException``
around its imports) and surface later as an unrelated error; a second Ctrl-C stops at once. Shards
are zip archives of ``.npy`` members (readable with ``numpy.load``) written with fixed timestamps
and deflate level 1, so equal seeds give byte-identical files.

Errors are one line naming the file and what to do, as :class:`ShardError` (a ``ValueError``):
:class:`CorruptShardError` (a file that cannot be read), :class:`ProvenanceError` (a shard or index
of another render), :class:`MetaFileError` (a ``meta.json`` that is not a render record).
"""

from __future__ import annotations

import io
import json
import os
import signal
import threading
import time
import zipfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..._io import atomic_write_bytes, atomic_write_json
from ...symmetry import SHAPES
from .poses import _SPLIT_CODES, check_spec, default_variant, pose_digest, sample_poses
from .render import (
    FOV_DEG,
    LOOKS,
    MIN_IMAGE_SIZE,
    SCENE_DISTANCE,
    SCENE_VERSION,
    Look,
    SymsolRenderer,
    intrinsics,
)
from .shapes import shape_name

FORMAT = "posediff-symsol/3"
#: The format before shards recorded their provenance (refused: such folders cannot be checked).
LEGACY_FORMATS = ("posediff-symsol/1",)
#: Formats of posediff's first scene (refused: their images are not the paper's).
OLD_SCENE_FORMATS = ("posediff-symsol/2",)
#: The stream of the per-image looks (``look=varied``), apart from the poses'.
_LOOK_STREAM = 7
DEPTH_SCALE = 1e-3  # one depth unit = 1e-3 scene units; uint16 covers 0 … 65.5
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


# ----------------------------------------------------------------------------- errors
class ShardError(ValueError, RuntimeError):
    """A rendered split that cannot be used as it is; the message is one line naming the file and
    what to do. A ``ValueError`` (the commands print data errors as one line) and, as the errors of
    earlier versions were, a ``RuntimeError``.

    Re-raised in the main process from a ``DataLoader`` worker, torch builds the exception again
    from the worker's whole traceback; the one line is recovered from it (the traceback is kept in
    ``worker_traceback``)."""

    def __init__(self, message: object = "", *args: object) -> None:
        text = str(message)
        self.worker_traceback: str | None = None
        if "\n" in text:
            self.worker_traceback = text
            text = _own_line(type(self), text)
        super().__init__(text, *args)


class CorruptShardError(ShardError):
    """A shard (or ``index.npz``) that cannot be read: truncated, random bytes, bad arrays."""


class ProvenanceError(ShardError):
    """A shard or index that belongs to another render than the one asked for (or than
    ``meta.json`` describes), or a shard without a provenance record."""


class MetaFileError(ShardError):
    """A ``meta.json`` that is not a render record of this format (bad JSON, not an object,
    missing or malformed keys, an older format)."""


def _own_line(cls: type, text: str) -> str:
    """The message of a ``cls`` exception in a formatted traceback (its last line naming ``cls``)."""
    names = (f"{cls.__module__}.{cls.__qualname__}: ", f"{cls.__qualname__}: ")
    lines = text.splitlines()
    for line in reversed(lines):
        for name in names:
            if line.startswith(name):
                return line[len(name) :].strip()
    return next((line.strip() for line in lines if line.strip()), "")


def _one_line(e: BaseException, limit: int = 160) -> str:
    text = " ".join(str(e).split())
    text = text if len(text) <= limit else text[: limit - 1] + "…"
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _corrupt(path: Path, e: BaseException) -> CorruptShardError:
    what = "shard" if path.name.startswith("shard-") else "file"
    todo = (
        "delete it and run the same posediff data render again (it renders only the missing shards)"
        if what == "shard"
        else "run the same posediff data render again (it rewrites it)"
    )
    return CorruptShardError(f"corrupt {what} {path} ({_one_line(e)}); {todo}")


# ----------------------------------------------------------------------------- files
def render_command(dataset: str, variant: str, split: str, root: Path | str, n_per_shape: Any = "N") -> str:
    """The command that makes a split (for error messages)."""
    return (
        f"posediff data render dataset={dataset} variant={variant} split={split} "
        f"n_per_shape={n_per_shape} out={root}"
    )


def shard_path(split_dir: Path, k: int) -> Path:
    """Where shard ``k`` of a split lives."""
    return split_dir / f"shard-{k:05d}.npz"


def _shard_number(path: Path) -> int | None:
    digits = path.name[len("shard-") : -len(".npz")]
    return int(digits) if digits.isdigit() else None


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an ``.npz`` atomically and byte-reproducibly (fixed zip timestamps)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, arr in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue(), compresslevel=1)
    atomic_write_bytes(path, buf.getvalue())


def read_npz(path: Path, keys: Sequence[str], optional: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Load ``keys`` (and those of ``optional`` that it holds) from an ``.npz``; any damage →
    one-line :class:`CorruptShardError` naming the file (a missing file stays a
    ``FileNotFoundError``)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in (*keys, *(k for k in optional if k in z.files))}
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 — zip, zlib, npy-header, memory errors: all mean "damaged"
        raise _corrupt(path, e) from e


def _read_record(path: Path) -> dict[str, Any] | None:
    """A shard's provenance record; ``None`` when it has none (an older format)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "provenance" not in z.files:
                return None
            arr = z["provenance"]
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001
        raise _corrupt(path, e) from e
    return _parse_record(path, arr)


def _parse_record(path: Path, arr: np.ndarray) -> dict[str, Any]:
    try:
        if arr.shape != (1,) or arr.dtype.kind != "U":
            raise ValueError(f"provenance is a {arr.dtype} array of shape {arr.shape}, not one string")
        record = json.loads(str(arr.item()))
        if not isinstance(record, dict):
            raise ValueError(f"provenance holds a JSON {type(record).__name__}, not an object")
    except ValueError as e:
        raise _corrupt(path, e) from e
    return record


# ----------------------------------------------------------------------------- provenance
#: What defines a render's content (compared on resume; a shard records these too).
_SPEC_KEYS = (
    "format",
    "dataset",
    "variant",
    "split",
    "n_per_shape",
    "shapes",
    "seed",
    "image_size",
    "fov_deg",
    "shard_size",
    "depth_scale",
    "look",
    "renderer",
    "poses_sha256",
)
#: What follows from the others (named in a mismatch only when nothing above differs).
_DERIVED_KEYS = ("poses_sha256", "num_samples", "num_shards", "start", "stop")
_META_TYPES: dict[str, Any] = {
    "format": str,
    "dataset": str,
    "variant": str,
    "split": str,
    "n_per_shape": int,
    "shapes": list,
    "seed": int,
    "image_size": int,
    "fov_deg": (int, float),
    "shard_size": int,
    "depth_scale": (int, float),
    "look": str,
    "renderer": dict,
    "poses_sha256": str,
    "K": list,
    "num_samples": int,
    "num_shards": int,
    "complete": bool,
}


def _json(value: Any) -> Any:
    """``value`` as it reads back from JSON (tuples → lists, …), for comparisons with files."""
    return json.loads(json.dumps(value))


def _spec(meta: dict[str, Any]) -> dict[str, Any]:
    return {k: meta.get(k) for k in _SPEC_KEYS}


def _shard_record(meta: dict[str, Any], k: int, digest: str) -> dict[str, Any]:
    """What shard ``k`` of the render ``meta`` records: the render's spec, its place and its poses."""
    size, n = int(meta["shard_size"]), int(meta["num_samples"])
    record = {key: meta[key] for key in _SPEC_KEYS if key != "poses_sha256"}
    record.update(
        num_samples=n,
        num_shards=int(meta["num_shards"]),
        shard=int(k),
        start=k * size,
        stop=min(n, (k + 1) * size),
        poses_sha256=digest,
    )
    return _json(record)


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _short(v: Any) -> str:
    if isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v):
        return v[:12] + "…"
    return "missing" if v is None else repr(v)


def _diff(got: dict[str, Any], want: dict[str, Any], got_where: str, want_where: str) -> str:
    """The fields in which ``got`` differs from ``want``, as ``"seed 0 in X, 1 in Y"``; the derived
    ones (pose digest, sizes) only when nothing else differs."""
    a, b = _flat(got), _flat(want)
    keys = [k for k in dict.fromkeys([*b, *a]) if a.get(k) != b.get(k)]
    primary = [k for k in keys if k.split(".")[0] not in _DERIVED_KEYS]
    return ", ".join(
        f"{k} {_short(a.get(k))} {got_where}, {_short(b.get(k))} {want_where}" for k in (primary or keys)
    )


def read_meta(meta_path: Path, todo: str) -> dict[str, Any]:
    """``meta.json`` checked to be a render record of :data:`FORMAT` with every key; else a one-line
    :class:`MetaFileError` naming the file and ending with ``todo`` (what to do)."""
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise MetaFileError(f"{meta_path} is not valid JSON ({e.msg} at line {e.lineno}); {todo}") from e
    except (OSError, UnicodeDecodeError) as e:
        raise MetaFileError(f"cannot read {meta_path} ({_one_line(e)}); {todo}") from e
    if not isinstance(meta, dict):
        raise MetaFileError(
            f"{meta_path} holds a JSON {type(meta).__name__}, not a render record (an object with "
            f"format, dataset, split, seed, …); {todo}"
        )
    if meta.get("format") in LEGACY_FORMATS:
        raise MetaFileError(
            f"{meta_path} is from an older posediff (format {meta['format']}: its shards record no "
            f"provenance, so they cannot be checked against their poses); {todo}"
        )
    if meta.get("format") in OLD_SCENE_FORMATS:
        raise MetaFileError(
            f"{meta_path} holds posediff's first scene (format {meta['format']}: an icosahedron 1.9× smaller "
            f"than the paper's, other lighting; scene {SCENE_VERSION} is the paper's); {todo}"
        )
    if meta.get("format") != FORMAT:
        raise MetaFileError(f"{meta_path} has format {meta.get('format')!r}, not {FORMAT!r}; {todo}")
    missing = [k for k in _META_TYPES if k not in meta]
    if missing:
        raise MetaFileError(f"{meta_path} lacks {', '.join(missing)}; {todo}")
    for k, kind in _META_TYPES.items():
        if isinstance(meta[k], bool) is not (kind is bool) or not isinstance(meta[k], kind):
            raise MetaFileError(f"{meta_path} has a malformed {k} ({_short(meta[k])}); {todo}")
    return meta


def _check_count(name: str, value: Any, minimum: int, unit: str = "") -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}={value!r} is invalid: give an integer of at least {minimum}{unit}")
    return int(value)


# ----------------------------------------------------------------------------- rendering
@dataclass
class RenderSummary:
    path: Path
    images: int
    rendered: int
    seconds: float

    def line(self) -> str:
        rate = self.rendered / self.seconds if self.seconds > 0 else float("nan")
        return (
            f"{self.images} images in {self.path} ({self.rendered} rendered now) in {self.seconds:.1f} s, "
            f"{rate:.1f} images/s"
        )


def image_look(look: str, seed: int, split: str, index: int) -> Look:
    """The look of image ``index`` of a split rendered with ``look`` (module docstring)."""
    if look == "paper":
        return Look.paper()
    rng = np.random.default_rng(
        np.random.SeedSequence([int(seed), _SPLIT_CODES[split], _LOOK_STREAM, int(index)])
    )
    return Look.sample(rng)


def _render_shard(args: tuple[Any, ...]) -> int:
    path, image_size, idx, shape_id, R, t, record, look, seed, split = args
    renderer = _worker_renderer(image_size)
    n = len(idx)
    rgb = np.empty((n, image_size, image_size, 3), np.uint8)
    depth = np.empty((n, image_size, image_size), np.uint16)
    with _sigint_between_images() as interrupted:
        for j in range(n):
            out = renderer.render(int(shape_id[j]), R[j], t[j], image_look(look, seed, split, int(idx[j])))
            rgb[j] = out.rgb
            depth[j] = np.round(out.depth / DEPTH_SCALE).astype(np.uint16)
            if interrupted():
                raise KeyboardInterrupt
    write_npz(
        path, {"rgb": rgb, "depth": depth, "index": idx.astype(np.int64), "provenance": np.array([record])}
    )
    return n


_RENDERERS: dict[int, SymsolRenderer] = {}


def _worker_renderer(image_size: int) -> SymsolRenderer:
    if image_size not in _RENDERERS:
        _RENDERERS[image_size] = SymsolRenderer(image_size)
    return _RENDERERS[image_size]


@contextmanager
def _sigint_between_images() -> Iterator[Any]:
    """Defer the first Ctrl-C to the caller's next check (``interrupted()``); a second one raises at
    once. Nothing changes off the main thread or where SIGINT is ignored (a pool worker, a background
    job) or handled by someone else than Python's default."""
    flag: list[bool] = []
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield lambda: False
        return

    def handler(signum: int, frame: Any) -> None:
        if flag:
            raise KeyboardInterrupt
        flag.append(True)

    signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: bool(flag)
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _ignore_sigint() -> None:
    """Pool initializer: Ctrl-C is the parent's to handle (it terminates the pool)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the pool's processes start, so they start ignoring it (no traceback of
    theirs on Ctrl-C, even before their initializer has run)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:  # None: a handler not set from Python, which cannot be put back; the default then
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)


def _render_in_pool(todo: list[tuple[Any, ...]], workers: int, root: Path, bar: Any) -> None:
    import multiprocessing as mp

    temporary = ".shard-*.npz.*.tmp"  # posediff._io.atomic_write_bytes' temporary names
    before = set(root.glob(temporary))
    with _sigint_ignored():
        pool = mp.get_context("spawn").Pool(min(workers, len(todo)), initializer=_ignore_sigint)
    try:
        for done in pool.imap_unordered(_render_shard, todo):
            bar.update(done)
        pool.close()
    except BaseException:
        pool.terminate()  # kills the workers (and waits for them); their half-written files stay
        for tmp in set(root.glob(temporary)) - before:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        pool.join()


def _check_existing_shards(root: Path, records: list[dict[str, Any]]) -> set[int]:
    """The shards already in ``root`` that belong to the render ``records`` describes; any other
    shard-*.npz (another render, no provenance, unreadable) → one-line error naming it."""
    todo = f"render into a new out= folder or delete {root} yourself"
    present: set[int] = set()
    for path in sorted(root.glob("shard-*.npz")):
        k = _shard_number(path)
        if k is None or k >= len(records):
            raise ProvenanceError(
                f"{path} is not part of this render (which has {len(records)} shards); {todo}"
            )
        record = _read_record(path)
        if record is None:
            raise ProvenanceError(
                f"{path} records no provenance (an older posediff rendered it), so it cannot be "
                f"checked against this render; {todo}"
            )
        diff = _diff(record, records[k], "in the shard", "asked for")
        if diff:
            raise ProvenanceError(f"{path} was rendered from other settings ({diff}); {todo}")
        present.add(k)
    return present


def render_dataset(
    out: str | os.PathLike[str],
    *,
    dataset: str = "symsolt",
    variant: str | None = None,
    split: str = "train",
    n_per_shape: int = 1000,
    image_size: int = 224,
    seed: int = 0,
    shapes: Sequence[str] = SHAPES,
    shard_size: int = 256,
    workers: int = 1,
    progress: bool = True,
    look: str = "paper",
) -> RenderSummary:
    """Render one split into ``<out>/<split>/`` (module docstring); resumes an interrupted run.

    ``workers`` > 1 renders shards in that many processes (each with its own GL context); 0 or 1
    renders in this process. ``look``: ``paper`` or ``varied`` (module docstring). Every option is
    checked before anything is written. A folder that
    holds a different dataset (other seed, size, …, in ``meta.json`` or in any shard) is refused
    with a one-line error.
    """
    variant = check_spec(dataset, variant, split)
    n_per_shape = _check_count("n_per_shape", n_per_shape, 1)
    image_size = _check_count("image_size", image_size, MIN_IMAGE_SIZE, " (pixels)")
    shard_size = _check_count("shard_size", shard_size, 1)
    workers = _check_count("workers", workers, 0, " (0 or 1: render in this process)")
    seed = _check_count("seed", seed, 0)
    if look not in LOOKS:
        raise ValueError(f"unknown look {look!r}; available: {', '.join(LOOKS)}")
    poses = sample_poses(dataset, variant, split, n_per_shape, seed, shapes)  # checks the shapes
    root = Path(out) / split
    for folder in (Path(out), root):
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"{folder} is a file, not a folder; choose another out=")
    n = len(poses)
    num_shards = (n + shard_size - 1) // shard_size
    meta: dict[str, Any] = {
        "format": FORMAT,
        "dataset": dataset,
        "variant": variant,
        "split": split,
        "n_per_shape": n_per_shape,
        "shapes": [shape_name(s) for s in shapes],
        "seed": seed,
        "image_size": image_size,
        "fov_deg": FOV_DEG,
        "shard_size": shard_size,
        "scene_distance": SCENE_DISTANCE,
        "depth_scale": DEPTH_SCALE,
        "look": look,
        "renderer": SymsolRenderer(image_size).settings(),
        "poses_sha256": poses.digest(),
        "K": intrinsics(image_size).tolist(),
        "num_samples": n,
        "num_shards": num_shards,
        "complete": False,
    }
    meta_path = root / "meta.json"
    todo_here = f"render into a new out= folder or delete {root} yourself"
    if meta_path.exists():
        old = read_meta(meta_path, todo_here)
        if _spec(old) != _json(_spec(meta)):
            raise ProvenanceError(
                f"{root} already holds another dataset ({_diff(_spec(old), _json(_spec(meta)), 'there', 'asked for')}); "
                f"{todo_here}"
            )
    records = [
        _shard_record(meta, k, poses.digest(k * shard_size, (k + 1) * shard_size)) for k in range(num_shards)
    ]
    present = _check_existing_shards(root, records) if root.is_dir() else set()
    # everything checked: from here on files are written
    atomic_write_json(meta_path, meta)
    write_npz(
        root / "index.npz",
        {
            "shape_id": poses.shape_id,
            "R": poses.R,
            "t": poses.t,
            "shard": np.arange(n) // shard_size,
            "offset": np.arange(n) % shard_size,
        },
    )
    todo = []
    for k in range(num_shards):
        if k in present:
            continue
        sl = slice(k * shard_size, min(n, (k + 1) * shard_size))
        record = json.dumps(records[k], sort_keys=True)
        todo.append(
            (
                shard_path(root, k),
                image_size,
                np.arange(n)[sl],
                poses.shape_id[sl],
                poses.R[sl],
                poses.t[sl],
                record,
                look,
                seed,
                split,
            )
        )
    rendered = sum(len(a[2]) for a in todo)
    t0 = time.perf_counter()
    from tqdm.auto import tqdm

    bar = tqdm(
        total=n, initial=n - rendered, unit="img", desc=f"{dataset}/{variant}/{split}", disable=not progress
    )
    try:
        if workers > 1 and len(todo) > 1:
            _render_in_pool(todo, workers, root, bar)
        else:
            for a in todo:
                bar.update(_render_shard(a))
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    meta["complete"] = True
    meta["render_seconds"] = round(seconds, 3)
    atomic_write_json(meta_path, meta)
    return RenderSummary(root, n, rendered, seconds)


# ----------------------------------------------------------------------------- reading
class SymsolShards:
    """A rendered split (``<root>/<split>/`` or the split folder itself): its meta, index and shards.

    Missing or unfinished folders raise one-line errors naming the path and the command that makes
    (or finishes) them. Opening a split checks ``meta.json`` (a render record of this format),
    ``index.npz`` (the poses ``meta.json`` records) and the provenance of every shard (the render
    and the poses ``meta.json`` and ``index.npz`` describe): an unreadable file raises
    :class:`CorruptShardError`, a shard or index of another render :class:`ProvenanceError`, both
    one line naming the file. :meth:`load_shard` checks the shard it loads again.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        dataset: str = "symsolt",
        variant: str | None = None,
        split: str | None = None,
    ) -> None:
        path = Path(path)
        if split is not None and (path / split / "meta.json").exists():
            path = path / split
        meta_path = path / "meta.json"
        want_split = split or "train"
        variant = variant or default_variant(dataset)
        if not meta_path.exists():
            root = path.parent if path.name == want_split else path
            raise FileNotFoundError(
                f"no rendered {dataset} {want_split} split at {root / want_split}; make it with: "
                + render_command(dataset, variant, want_split, root)
            )
        again = "render the split again into a new folder: " + render_command(
            dataset, variant, want_split, "NEW_FOLDER"
        )
        self.meta: dict[str, Any] = read_meta(meta_path, again)
        m = self.meta
        if not m["complete"]:
            raise ShardError(
                f"{path} is unfinished ({sum(1 for _ in path.glob('shard-*.npz'))} of {m['num_shards']} shards); "
                "finish it with: "
                + render_command(m["dataset"], m["variant"], m["split"], path.parent, m["n_per_shape"])
                + f" image_size={m['image_size']} seed={m['seed']} shard_size={m['shard_size']}"
            )
        self.path = path
        self._again = "the folder mixes renders: " + again
        self.index = read_npz(path / "index.npz", ("shape_id", "R", "t", "shard", "offset"))
        self._check_index()
        self.K = np.asarray(m["K"], dtype=np.float64)
        self._records = [self._expected_record(k) for k in range(self.num_shards)]
        for k in range(self.num_shards):
            self._check_record(k, _read_record(self._existing(k)))

    # -- checks
    def _check_index(self) -> None:
        m, ix = self.meta, self.index
        where = self.path / "index.npz"
        n, size = int(m["num_samples"]), int(m["shard_size"])
        want = {"shape_id": (n,), "R": (n, 3, 3), "t": (n, 3), "shard": (n,), "offset": (n,)}
        for key, shape in want.items():
            if ix[key].shape != shape:
                raise CorruptShardError(
                    f"corrupt file {where}: {key} has shape {ix[key].shape}, {shape} expected from "
                    f"{self.path / 'meta.json'}; {self._again}"
                )
        if (
            n != int(m["n_per_shape"]) * len(m["shapes"])
            or m["num_shards"] != (n + size - 1) // size
            or not np.array_equal(ix["shard"], np.arange(n) // size)
            or not np.array_equal(ix["offset"], np.arange(n) % size)
        ):
            raise ProvenanceError(
                f"{where} does not match {self.path / 'meta.json'} (sample or shard counts differ); {self._again}"
            )
        digest = pose_digest(ix["shape_id"], ix["R"], ix["t"])
        if digest != m["poses_sha256"]:
            raise ProvenanceError(
                f"{where} holds other poses than {self.path / 'meta.json'} records "
                f"(poses_sha256 {_short(digest)} there, {_short(m['poses_sha256'])} in meta.json); {self._again}"
            )

    def _expected_record(self, k: int) -> dict[str, Any]:
        size, n = self.shard_size, len(self)
        start, stop = k * size, min(n, (k + 1) * size)
        ix = self.index
        digest = pose_digest(ix["shape_id"][start:stop], ix["R"][start:stop], ix["t"][start:stop])
        return _shard_record(self.meta, k, digest)

    def _existing(self, k: int) -> Path:
        path = self.shard_path(k)
        if not path.exists():
            raise FileNotFoundError(
                f"missing shard {path} (the split's meta.json says it is complete); run the same "
                "posediff data render again (it renders only the missing shards)"
            )
        return path

    def _check_record(self, k: int, record: dict[str, Any] | None) -> None:
        path = self.shard_path(k)
        if record is None:
            raise ProvenanceError(
                f"{path} records no provenance (an older posediff, or not posediff data render, wrote it); "
                + self._again
            )
        diff = _diff(record, self._records[k], "in the shard", "in meta.json/index.npz")
        if diff:
            raise ProvenanceError(f"{path} does not belong to this split ({diff}); {self._again}")

    # -- access
    def __len__(self) -> int:
        return int(self.meta["num_samples"])

    @property
    def num_shards(self) -> int:
        return int(self.meta["num_shards"])

    @property
    def shard_size(self) -> int:
        return int(self.meta["shard_size"])

    @property
    def image_size(self) -> int:
        return int(self.meta["image_size"])

    def shard_path(self, k: int) -> Path:
        return shard_path(self.path, k)

    def load_shard(self, k: int, *, depth: bool = True) -> dict[str, np.ndarray]:
        """Shard ``k`` as arrays: ``rgb``, ``index`` and, with ``depth`` (skip it to read and
        inflate half as much), ``depth`` (float32, scene units) and ``mask``. A damaged shard →
        :class:`CorruptShardError`, one of another render → :class:`ProvenanceError` (one line,
        naming the file; also when raised in a ``DataLoader`` worker)."""
        path = self._existing(k)
        z = read_npz(path, ("rgb", "depth", "index") if depth else ("rgb", "index"), ("provenance",))
        self._check_record(k, _parse_record(path, z["provenance"]) if "provenance" in z else None)
        n = len(z["index"])
        s = self.image_size
        record = self._records[k]
        if not np.array_equal(z["index"], np.arange(record["start"], record["stop"])):
            raise CorruptShardError(
                f"corrupt shard {path}: its index is not {record['start']}…{record['stop'] - 1}; "
                "delete it and run the same posediff data render again"
            )
        if z["rgb"].shape != (n, s, s, 3) or (depth and z["depth"].shape != (n, s, s)):
            shapes = f"rgb {z['rgb'].shape}" + (f", depth {z['depth'].shape}" if depth else "")
            raise CorruptShardError(
                f"corrupt shard {path}: {shapes}, expected ({n}, {s}, {s}[, 3]); "
                "delete it and run the same posediff data render again"
            )
        out = {"rgb": z["rgb"], "index": z["index"]}
        if depth:
            out["depth"] = z["depth"].astype(np.float32) * float(self.meta["depth_scale"])
            out["mask"] = z["depth"] > 0
        return out

    def iter_samples(self, shards: Sequence[int] | None = None) -> Iterator[dict[str, Any]]:
        """Every sample of the given shards (all by default) in file order."""
        for k in range(self.num_shards) if shards is None else shards:
            z = self.load_shard(k)
            for j, i in enumerate(z["index"]):
                yield {
                    "rgb": z["rgb"][j],
                    "depth": z["depth"][j],
                    "mask": z["mask"][j],
                    "shape_id": int(self.index["shape_id"][i]),
                    "R": self.index["R"][i],
                    "t": self.index["t"][i],
                    "K": self.K,
                    "index": int(i),
                }


__all__ = [
    "DEPTH_SCALE",
    "FORMAT",
    "CorruptShardError",
    "MetaFileError",
    "ProvenanceError",
    "RenderSummary",
    "ShardError",
    "SymsolShards",
    "read_meta",
    "read_npz",
    "render_command",
    "render_dataset",
    "shard_path",
    "write_npz",
]
