"""On-disk SYMSOL / SYMSOL-T: shards that stream, an index, atomic and resumable rendering.

Layout of one split, ``<out>/<split>/``::

    meta.json             what was asked for (dataset, variant, split, seed, sizes, K, renderer) and
                          ``complete`` (false until the last shard is written)
    index.npz             per sample: shape_id, R (3×3), t (3, camera frame), shard, offset
    shard-00000.npz …     ``shard_size`` samples each: rgb (n, H, W, 3) uint8, depth (n, H, W) uint16
                          in units of ``depth_scale`` (0 = background; mask = depth > 0), index (n,)

Every file is written to a temporary name in the same folder and renamed, so an interrupted render
leaves only whole shards; running the same command again renders only the missing ones. Shards
are zip archives of ``.npy`` members (readable with ``numpy.load``) written with fixed timestamps
and deflate level 1, so equal seeds give byte-identical files.
"""

from __future__ import annotations

import io
import json
import os
import time
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..._io import atomic_write_bytes, atomic_write_json
from ...symmetry import SHAPES
from .poses import check_spec, default_variant, sample_poses
from .render import FOV_DEG, SCENE_DISTANCE, SymsolRenderer, intrinsics

FORMAT = "posediff-symsol/1"
DEPTH_SCALE = 1e-3  # one depth unit = 1e-3 scene units; uint16 covers 0 … 65.5
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def render_command(dataset: str, variant: str, split: str, root: Path | str, n_per_shape: Any = "N") -> str:
    """The command that makes a split (for error messages)."""
    return (
        f"posediff data render dataset={dataset} variant={variant} split={split} "
        f"n_per_shape={n_per_shape} out={root}"
    )


def shard_path(split_dir: Path, k: int) -> Path:
    """Where shard ``k`` of a split lives."""
    return split_dir / f"shard-{k:05d}.npz"


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


def read_npz(path: Path, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """Load ``keys`` from an ``.npz``; any damage → ``RuntimeError`` naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in keys}
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, ValueError, KeyError, EOFError, OSError) as e:
        raise RuntimeError(
            f"corrupt shard {path}: {type(e).__name__}: {e} — delete it and render again"
        ) from e


def _spec(cfg: dict[str, Any]) -> dict[str, Any]:
    keys = (
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
    )
    return {k: cfg[k] for k in keys}


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


def _render_shard(args: tuple[Path, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> int:
    path, image_size, idx, shape_id, R, t = args
    renderer = _worker_renderer(image_size)
    n = len(idx)
    rgb = np.empty((n, image_size, image_size, 3), np.uint8)
    depth = np.empty((n, image_size, image_size), np.uint16)
    for j in range(n):
        out = renderer.render(int(shape_id[j]), R[j], t[j])
        rgb[j] = out.rgb
        depth[j] = np.round(out.depth / DEPTH_SCALE).astype(np.uint16)
    write_npz(path, {"rgb": rgb, "depth": depth, "index": idx.astype(np.int64)})
    return n


_RENDERERS: dict[int, SymsolRenderer] = {}


def _worker_renderer(image_size: int) -> SymsolRenderer:
    if image_size not in _RENDERERS:
        _RENDERERS[image_size] = SymsolRenderer(image_size)
    return _RENDERERS[image_size]


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
) -> RenderSummary:
    """Render one split into ``<out>/<split>/`` (module docstring); resumes an interrupted run.

    ``workers`` > 1 renders shards in that many processes (each with its own GL context). A folder
    that holds a different dataset (other seed, size, …) is refused with a one-line error.
    """
    variant = check_spec(dataset, variant, split)
    if shard_size < 1:
        raise ValueError(f"shard_size must be at least 1, got {shard_size}")
    root = Path(out) / split
    poses = sample_poses(dataset, variant, split, n_per_shape, seed, shapes)
    n = len(poses)
    num_shards = (n + shard_size - 1) // shard_size
    meta: dict[str, Any] = {
        "format": FORMAT,
        "dataset": dataset,
        "variant": variant,
        "split": split,
        "n_per_shape": int(n_per_shape),
        "shapes": list(shapes),
        "seed": int(seed),
        "image_size": int(image_size),
        "fov_deg": FOV_DEG,
        "shard_size": int(shard_size),
        "scene_distance": SCENE_DISTANCE,
        "depth_scale": DEPTH_SCALE,
        "K": intrinsics(image_size).tolist(),
        "num_samples": n,
        "num_shards": num_shards,
        "complete": False,
    }
    meta_path = root / "meta.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if old.get("format") != FORMAT or _spec(old) != _spec(meta):
            diff = {k: (old.get(k), v) for k, v in _spec(meta).items() if old.get(k) != v}
            raise ValueError(
                f"{root} already holds another dataset (differs in {diff}); choose another out= or delete it"
            )
    atomic_write_json(meta_path, meta)
    shard_of = np.arange(n) // shard_size
    write_npz(
        root / "index.npz",
        {
            "shape_id": poses.shape_id,
            "R": poses.R,
            "t": poses.t,
            "shard": shard_of,
            "offset": np.arange(n) % shard_size,
        },
    )
    todo = []
    for k in range(num_shards):
        path = shard_path(root, k)
        if path.exists():
            continue
        sl = slice(k * shard_size, min(n, (k + 1) * shard_size))
        idx = np.arange(n)[sl]
        todo.append((path, image_size, idx, poses.shape_id[sl], poses.R[sl], poses.t[sl]))
    rendered = sum(len(a[2]) for a in todo)
    t0 = time.perf_counter()
    from tqdm.auto import tqdm

    bar = tqdm(
        total=n, initial=n - rendered, unit="img", desc=f"{dataset}/{variant}/{split}", disable=not progress
    )
    try:
        if workers > 1 and len(todo) > 1:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(workers) as pool:
                for done in pool.imap_unordered(_render_shard, todo):
                    bar.update(done)
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


class SymsolShards:
    """A rendered split (``<root>/<split>/`` or the split folder itself): its meta, index and shards.

    Missing or unfinished folders raise one-line errors naming the path and the command that makes
    (or finishes) them; damaged shards raise naming the file.
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
        if not meta_path.exists():
            want_split = split or "train"
            root = path.parent if path.name == want_split else path
            variant = variant or default_variant(dataset)
            raise FileNotFoundError(
                f"no rendered {dataset} {want_split} split at {root / want_split}; make it with: "
                + render_command(dataset, variant, want_split, root)
            )
        try:
            self.meta: dict[str, Any] = json.loads(meta_path.read_text())
        except json.JSONDecodeError as e:
            raise RuntimeError(f"corrupt {meta_path}: {e}") from e
        m = self.meta
        if not m.get("complete"):
            raise RuntimeError(
                f"{path} is unfinished ({sum(1 for _ in path.glob('shard-*.npz'))} of {m.get('num_shards')} shards); "
                "finish it with: "
                + render_command(m["dataset"], m["variant"], m["split"], path.parent, m["n_per_shape"])
                + f" image_size={m['image_size']} seed={m['seed']}"
            )
        self.path = path
        self.index = read_npz(path / "index.npz", ("shape_id", "R", "t", "shard", "offset"))
        self.K = np.asarray(m["K"], dtype=np.float64)

    def __len__(self) -> int:
        return int(self.meta["num_samples"])

    @property
    def num_shards(self) -> int:
        return int(self.meta["num_shards"])

    @property
    def image_size(self) -> int:
        return int(self.meta["image_size"])

    def shard_path(self, k: int) -> Path:
        return shard_path(self.path, k)

    def load_shard(self, k: int, *, depth: bool = True) -> dict[str, np.ndarray]:
        """Shard ``k`` as arrays: ``rgb``, ``index`` and, with ``depth`` (skip it to read and
        inflate half as much), ``depth`` (float32, scene units) and ``mask``."""
        path = self.shard_path(k)
        if not path.exists():
            raise FileNotFoundError(
                f"missing shard {path} (the split's meta.json says it is complete; render it again)"
            )
        z = read_npz(path, ("rgb", "depth", "index") if depth else ("rgb", "index"))
        n = len(z["index"])
        s = self.image_size
        if z["rgb"].shape != (n, s, s, 3) or (depth and z["depth"].shape != (n, s, s)):
            shapes = f"rgb {z['rgb'].shape}" + (f", depth {z['depth'].shape}" if depth else "")
            raise RuntimeError(f"corrupt shard {path}: {shapes}, expected ({n}, {s}, {s}[, 3])")
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
    "RenderSummary",
    "SymsolShards",
    "read_npz",
    "render_command",
    "render_dataset",
    "shard_path",
    "write_npz",
]
