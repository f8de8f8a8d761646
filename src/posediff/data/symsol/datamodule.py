"""SYMSOL / SYMSOL-T as PyTorch datasets and a Lightning ``DataModule``.

Two modes:

* ``shards`` (training): streams the shards written by ``posediff data render`` — each epoch the
  shards are shuffled and split across DDP ranks and ``DataLoader`` workers, and the samples within
  a shard are shuffled; memory holds one shard per worker.
* ``render`` (quick runs, no files): renders every sample on the fly from its seeded pose; each
  worker process creates its own renderer on first use.

A sample (and, stacked, a batch) is a dict with the same keys as the toy's, so the training and
evaluation code serve both: ``image`` (3, H, W) float32 in [0, 1]; ``pose`` the diffusion target —
``R`` (3, 3) for a rotation group, else ``[R | t − c]`` (4, 4) with the translation from the scene
centre c = (0, 0, SCENE_DISTANCE) (in [−1, 1]³ for SYMSOL-T); ``rotation`` (3, 3); ``translation``
(3,) from the scene centre; ``shape`` int64, the index in ``SHAPES`` (look up the equivalent poses
with :func:`~posediff.data.symsol.equivalent_poses`); ``camera_pose`` (4, 4) the camera-frame
[R | t]; ``K`` (3, 3); ``index``; with ``with_depth=True`` also ``mask`` (H, W) bool and
``depth`` (H, W) float32.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from ...lie import LieGroup, get_group
from ...symmetry import SHAPES
from ..protocol import LoaderPredictions
from ..resumable import ResumableDataLoader, eval_loader
from .poses import check_spec, sample_poses
from .render import SCENE_DISTANCE, SymsolRenderer, intrinsics
from .shards import SymsolShards

_CENTRE = np.array([0.0, 0.0, SCENE_DISTANCE])


def to_sample(
    rgb: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    shape_id: int,
    K: np.ndarray,
    index: int,
    mask: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    *,
    rotation_only: bool = False,
) -> dict[str, Any]:
    """One sample as tensors (module docstring); ``rotation_only``: ``pose`` is ``R`` (3, 3)."""
    camera = np.eye(4, dtype=np.float32)
    camera[:3, :3], camera[:3, 3] = R, t
    target = camera.copy()
    target[:3, 3] = t - _CENTRE
    out = {
        "image": torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).float().div_(255.0),
        "pose": torch.from_numpy(np.ascontiguousarray(target[:3, :3]) if rotation_only else target),
        "rotation": torch.from_numpy(np.asarray(R, dtype=np.float32)),
        "translation": torch.from_numpy(np.asarray(t - _CENTRE, dtype=np.float32)),
        "shape": torch.tensor(shape_id, dtype=torch.int64),
        "camera_pose": torch.from_numpy(camera),
        "K": torch.from_numpy(np.asarray(K, dtype=np.float32)),
        "index": torch.tensor(index, dtype=torch.int64),
    }
    if mask is not None and depth is not None:
        out["mask"] = torch.from_numpy(np.ascontiguousarray(mask))
        out["depth"] = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
    return out


class SymsolRenderDataset(Dataset):
    """Renders sample ``i`` of a split on the fly (map-style; deterministic per index)."""

    def __init__(
        self,
        dataset: str = "symsolt",
        variant: str | None = None,
        split: str = "train",
        n_per_shape: int = 1000,
        image_size: int = 224,
        seed: int = 0,
        shapes: Sequence[str] = SHAPES,
        with_depth: bool = False,
        rotation_only: bool = False,
    ) -> None:
        self.variant = check_spec(dataset, variant, split)
        self.rotation_only = rotation_only
        self.poses = sample_poses(dataset, self.variant, split, n_per_shape, seed, shapes)
        self.image_size = int(image_size)
        self.K = intrinsics(self.image_size)
        self.with_depth = with_depth
        self._renderer: SymsolRenderer | None = None  # made lazily, in the process that renders

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, i: int) -> dict[str, Any]:
        if self._renderer is None:
            self._renderer = SymsolRenderer(self.image_size)
        p = self.poses
        out = self._renderer.render(int(p.shape_id[i]), p.R[i], p.t[i])
        extra = (out.mask, out.depth) if self.with_depth else (None, None)
        return to_sample(
            out.rgb,
            p.R[i],
            p.t[i],
            int(p.shape_id[i]),
            self.K,
            int(i),
            *extra,
            rotation_only=self.rotation_only,
        )

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_renderer"] = None
        return state


class SymsolShardDataset(IterableDataset):
    """Streams a rendered split. ``shuffle``: shard order and in-shard order change every epoch
    (seeded by ``seed`` and :meth:`set_epoch`); shards are split across DDP ranks, then workers.
    ``shapes``: only these shapes (names); ``limit_per_shape``: only the first that many samples of
    each shape (in index order); ``mask``: only the samples where this ``(N,)`` bool array is true
    (the train / validation hold-out). Shards without a kept sample are never read."""

    def __init__(
        self,
        shards: SymsolShards,
        *,
        shuffle: bool = True,
        seed: int = 0,
        with_depth: bool = False,
        rotation_only: bool = False,
        limit_per_shape: int | None = None,
        shapes: Sequence[str] | None = None,
        mask: np.ndarray | None = None,
    ) -> None:
        self.shards = shards
        self.rotation_only = rotation_only
        self.keep: np.ndarray | None = None if mask is None else np.asarray(mask, dtype=bool).copy()
        sid = np.asarray(shards.index["shape_id"])
        if shapes is not None:
            keep = np.isin(sid, [SHAPES.index(s) for s in shapes])
            self.keep = keep if self.keep is None else self.keep & keep
        if limit_per_shape is not None:
            rank = np.zeros(len(sid), dtype=np.int64)
            for k in np.unique(sid):
                sel = np.flatnonzero(sid == k)
                rank[sel] = np.arange(len(sel))
            keep = rank < int(limit_per_shape)
            self.keep = keep if self.keep is None else self.keep & keep
        self.shuffle = shuffle
        self.seed = seed
        self.with_depth = with_depth
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    @staticmethod
    def _rank_world() -> tuple[int, int]:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            return torch.distributed.get_rank(), torch.distributed.get_world_size()
        return 0, 1

    def _my_shards(self) -> list[int]:
        order = np.arange(self.shards.num_shards)
        if self.keep is not None:
            order = np.unique(np.asarray(self.shards.index["shard"])[self.keep])
        if self.shuffle:
            order = np.random.default_rng([self.seed, self.epoch]).permutation(order)
        rank, world = self._rank_world()
        order = order[rank::world]
        info = get_worker_info()
        if info is not None:
            order = order[info.id :: info.num_workers]
        return [int(k) for k in order]

    def __len__(self) -> int:
        _, world = self._rank_world()
        n = len(self.shards) if self.keep is None else int(self.keep.sum())
        return n // world

    def __iter__(self) -> Iterator[dict[str, Any]]:
        K = self.shards.K
        index = self.shards.index
        for k in self._my_shards():
            z = self.shards.load_shard(k, depth=self.with_depth)
            n = len(z["index"])
            order = (
                np.random.default_rng([self.seed, self.epoch, k]).permutation(n) if self.shuffle else range(n)
            )
            for j in order:
                i = int(z["index"][j])
                if self.keep is not None and not self.keep[i]:
                    continue
                extra = (z["mask"][j], z["depth"][j]) if self.with_depth else (None, None)
                yield to_sample(
                    z["rgb"][j],
                    index["R"][i],
                    index["t"][i],
                    int(index["shape_id"][i]),
                    K,
                    i,
                    *extra,
                    rotation_only=self.rotation_only,
                )


class SymsolDataModule(LoaderPredictions, L.LightningDataModule):
    """SYMSOL / SYMSOL-T train and test loaders (``conf/data/symsol*.yaml``).

    ``group`` (``so3`` / ``r3so3`` / ``se3``, a name or a group) sets the shape of ``pose``.
    ``mode="shards"`` reads ``<root>/train`` and ``<root>/test`` (made by ``posediff data render``;
    a missing folder → one line with the command that makes it); ``mode="render"`` renders
    ``n_per_shape_train`` / ``n_per_shape_test`` samples per shape on the fly at ``image_size``.
    In ``shards`` mode ``n_per_shape_test`` keeps the first that many test samples per shape
    (``None``: all).

    Validation (``val/loss``, which picks ``best.ckpt``) never reads the test split: in ``shards``
    mode it holds out the last ``val_fraction`` of the training samples in index order (at most
    ``max_val``, at least one; the shapes are interleaved, so the tail mixes them and sits in the
    last shards), which training then skips; in ``render`` mode it is a separately seeded draw
    from the training distribution (the ``val`` pose stream), ``val_fraction · n_per_shape_train``
    per shape (at most ``max_val`` in all). The training loader resumes mid-epoch exactly
    (:class:`~posediff.data.resumable.ResumableDataLoader`).
    """

    def __init__(
        self,
        dataset: str = "symsolt",
        variant: str | None = None,
        *,
        mode: str = "shards",
        root: str | None = None,
        image_size: int = 224,
        n_per_shape_train: int = 1000,
        n_per_shape_test: int | None = 100,
        shapes: Sequence[str] = SHAPES,
        seed: int = 0,
        batch_size: int = 16,
        num_workers: int = 0,
        with_depth: bool = False,
        group: LieGroup | str = "se3",
        val_fraction: float = 0.05,
        max_val: int = 1000,
    ) -> None:
        super().__init__()
        if not 0.0 < float(val_fraction) < 1.0 or int(max_val) < 1:
            raise ValueError(
                f"data.val_fraction must be in (0, 1) and data.max_val ≥ 1, got {val_fraction}, {max_val}"
            )
        self.val_fraction, self.max_val = float(val_fraction), int(max_val)
        self.group = get_group(group) if isinstance(group, str) else group
        if self.group.name not in ("so3", "se3", "r3so3"):
            raise ValueError(
                f"SYMSOL poses need a 3-D rotation group (so3, se3, r3so3), not {self.group.name!r}"
            )
        self.rotation_only = self.group.matrix_dim == 3
        if mode not in ("shards", "render"):
            raise ValueError(f"unknown data mode {mode!r}; available: shards, render")
        self.variant = check_spec(dataset, variant, "train")
        if mode == "shards" and not root:
            raise ValueError(
                f"data.root is not set: point it at a rendered {dataset} folder, or use data.mode=render"
            )
        self.dataset, self.mode, self.root = dataset, mode, root
        self.image_size, self.shapes, self.seed = int(image_size), tuple(shapes), seed
        self.n_per_shape = {"train": n_per_shape_train, "test": n_per_shape_test}
        self.n_per_shape["val"] = max(
            1, min(round(self.val_fraction * int(n_per_shape_train)), self.max_val // len(self.shapes))
        )
        self.batch_size, self.num_workers, self.with_depth = batch_size, num_workers, with_depth
        self.train: Dataset | None = None
        #: the validation samples (module docstring): never the test split
        self.val: Dataset | None = None
        self.test: Dataset | None = None

    def _split(self, split: str, mask: np.ndarray | None = None) -> Dataset:
        """``train`` / ``val`` / ``test``: in shards mode ``val`` reads the training folder (with the
        hold-out ``mask``); in render mode it is the ``val`` pose stream."""
        if self.mode == "render":
            return SymsolRenderDataset(
                self.dataset,
                self.variant,
                split,
                self.n_per_shape[split],
                self.image_size,
                self.seed,
                self.shapes,
                self.with_depth,
                self.rotation_only,
            )
        return self._shard_dataset(self._open_shards("test" if split == "test" else "train"), split, mask)

    def _open_shards(self, folder: str) -> SymsolShards:
        """``<root>/<folder>`` opened (the reader verifies meta, index and every shard's provenance)
        and checked against the config."""
        shards = SymsolShards(Path(str(self.root)), dataset=self.dataset, variant=self.variant, split=folder)
        m = shards.meta
        if (m["dataset"], m["variant"]) != (self.dataset, self.variant):
            raise ValueError(
                f"{shards.path} holds {m['dataset']}/{m['variant']}, but the config asks for {self.dataset}/{self.variant}"
            )
        missing = [s for s in self.shapes if s not in m["shapes"]]
        if missing:
            raise ValueError(
                f"{shards.path} holds the shapes {m['shapes']}, not {missing} (set data.shapes to a subset, or render them)"
            )
        if m["image_size"] != self.image_size:
            raise ValueError(
                f"{shards.path} was rendered at {m['image_size']} px, the config asks for {self.image_size} "
                f"(set data.image_size={m['image_size']} or render again)"
            )
        return shards

    def _shard_dataset(
        self, shards: SymsolShards, split: str, mask: np.ndarray | None = None
    ) -> SymsolShardDataset:
        """The ``train`` / ``val`` / ``test`` samples of opened ``shards`` (``mask``: the hold-out)."""
        m = shards.meta
        return SymsolShardDataset(
            shards,
            shuffle=split == "train",
            seed=self.seed,
            with_depth=self.with_depth,
            rotation_only=self.rotation_only,
            limit_per_shape=self.n_per_shape["test"] if split == "test" else None,
            shapes=None if tuple(m["shapes"]) == self.shapes else self.shapes,
            mask=mask,
        )

    def _train_and_val(self) -> tuple[Dataset, Dataset]:
        """The training set and the validation set (module docstring)."""
        if self.mode == "render":
            return self._split("train"), self._split("val")
        shards = self._open_shards("train")  # once: train and val share the opened folder
        train = self._shard_dataset(shards, "train")
        n = len(shards)
        kept = np.ones(n, dtype=bool) if train.keep is None else train.keep
        idx = np.flatnonzero(kept)
        n_val = min(self.max_val, max(1, round(self.val_fraction * len(idx))), len(idx) - 1)
        if n_val < 1:
            raise ValueError(f"{shards.path} has one training sample: nothing to hold out for validation")
        val = np.zeros(n, dtype=bool)
        val[idx[-n_val:]] = True
        return self._shard_dataset(shards, "train", mask=~val), self._shard_dataset(shards, "val", mask=val)

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit", "validate") and self.train is None:
            self.train, self.val = self._train_and_val()
        if stage in (None, "fit", "validate", "test", "predict") and self.test is None:
            self.test = self._split("test")

    def train_dataloader(self) -> DataLoader:
        """Shuffled training samples; resumes mid-epoch exactly (the shards' shuffle follows the pass)."""
        assert self.train is not None, "call setup() first"
        return ResumableDataLoader(
            self.train,
            batch_size=self.batch_size,
            shuffle=True,
            seed=self.seed,
            drop_last=True,
            num_workers=self.num_workers,
            persistent_workers=False,
        )

    def val_dataloader(self) -> DataLoader:
        """The validation samples (held out of training; never the test split)."""
        assert self.val is not None, "call setup('fit') first"
        return eval_loader(self.val, batch_size=self.batch_size, num_workers=self.num_workers)

    def test_dataloader(self) -> DataLoader:
        assert self.test is not None, "call setup() first"
        return eval_loader(self.test, batch_size=self.batch_size, num_workers=self.num_workers)

    @property
    def log_likelihood_default(self) -> bool:
        """Evaluations report the ground truth's log density by default on SYMSOL (rotation only)."""
        return self.dataset == "symsol" and self.rotation_only

    # ------------------------------------------------------------------ posediff.data.PoseDataModule
    def describe(self) -> str:
        where = f"shards in {self.root}" if self.mode == "shards" else "rendered on the fly"
        return f"{self.dataset} data ({where}): shapes {', '.join(self.shapes)}, {self.image_size} px"

    def prediction_input(self, index: int) -> dict[str, Any]:
        from .shapes import shape_name

        s = self.test_sample(index)
        K, offset = self.image_camera({"image_size": self.image_size})
        shape = shape_name(SHAPES[int(s["shape"])])
        return {"image": s["image"], "gt_pose": s["pose"], "shape": shape, "K": K, "camera_offset": offset,
                "info": {"shape": shape}}  # fmt: skip

    @classmethod
    def image_camera(cls, data_config: Any) -> tuple[Any, Any]:
        """The renderer's camera at the config's ``image_size`` and the scene centre's offset."""
        return intrinsics(int(data_config["image_size"])), np.array([0.0, 0.0, SCENE_DISTANCE])


__all__ = ["SymsolDataModule", "SymsolRenderDataset", "SymsolShardDataset", "to_sample"]
