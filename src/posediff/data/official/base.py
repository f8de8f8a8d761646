"""What the official-files data modules share (:mod:`.symsol`, :mod:`.symsolt`): the checked options,
one read per split, the file's symmetry sets for the scorer and as padded batch tensors, the
per-shape validation hold-out, the loaders and the comparison with posediff's groups."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ...lie import LieGroup, get_group
from ...symmetry import SHAPES, SymmetrySet
from ..protocol import LoaderPredictions
from ..resumable import ResumableDataLoader, eval_loader


class OfficialDataError(ValueError):
    """An official dataset folder or file posediff cannot read (one line naming it)."""


def padded_symmetries(
    symmetries: Mapping[str, np.ndarray], labels: Sequence[str]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every label's symmetry set ``(K, 3, 3)`` padded to the largest (identity rows, masked out):
    ``(len(labels), K_max, 3, 3)`` and the mask ``(len(labels), K_max)``; labels without a set are
    all masked."""
    size = max(len(S) for S in symmetries.values())
    sym = torch.eye(3).repeat(len(labels), size, 1, 1)
    mask = torch.zeros(len(labels), size, dtype=torch.bool)
    for s, S in symmetries.items():
        k = labels.index(s)
        sym[k, : len(S)] = torch.from_numpy(np.asarray(S, dtype=np.float32))
        mask[k, : len(S)] = True
    return sym, mask


class OfficialDataModule(LoaderPredictions, L.LightningDataModule):
    """The shared part of the official-files data modules. A subclass sets :attr:`labels` (what a
    batch's ``shape`` indexes) and :attr:`dataset_name`, and implements :meth:`_read` (a split's
    records: ``label`` (N,) indices into :attr:`labels`, ``symmetries`` shape → ``(K, 3, 3)``,
    ``source`` for messages) and :meth:`_dataset`. Validation holds out the last ``val_fraction`` of
    each shape's training records (at most ``max_val`` in all), which training skips."""

    labels: ClassVar[tuple[str, ...]] = SHAPES
    dataset_name: ClassVar[str] = "SYMSOL"
    #: the images are read from files and resized to ``image_size`` (so a checkpoint of another size
    #: can be evaluated on them: ``posediff eval`` sets it to the checkpoint's)
    resizes_images: ClassVar[bool] = True

    def __init__(
        self,
        root: str | None,
        root_hint: str,
        *,
        shapes: Sequence[str],
        image_size: int,
        n_per_shape_test: int | None,
        batch_size: int,
        num_workers: int,
        group: LieGroup | str,
        val_fraction: float,
        max_val: int,
        seed: int,
    ) -> None:
        super().__init__()
        if not root:
            raise OfficialDataError(f"data.root is not set: point it at {root_hint}")
        self.group = get_group(group) if isinstance(group, str) else group
        unknown = [s for s in shapes if s not in self.labels]
        if unknown or not shapes:
            raise OfficialDataError(
                f"unknown {self.dataset_name} shapes {unknown or '[]'}; available: {', '.join(self.labels)}"
            )
        if not 0.0 < float(val_fraction) < 1.0 or int(max_val) < 1:
            raise OfficialDataError(
                f"data.val_fraction must be in (0, 1) and data.max_val ≥ 1, got {val_fraction}, {max_val}"
            )
        self.root = Path(str(root)).expanduser()
        self.shapes, self.image_size = tuple(shapes), int(image_size)
        self.n_per_shape_test = None if n_per_shape_test is None else int(n_per_shape_test)
        self.batch_size, self.num_workers, self.seed = int(batch_size), int(num_workers), int(seed)
        self.val_fraction, self.max_val = float(val_fraction), int(max_val)
        self._read_splits: dict[str, Any] = {}
        self.train: Dataset | None = None
        self.val: Dataset | None = None
        self.test: Dataset | None = None
        #: shape → the file's symmetries as a :class:`~posediff.symmetry.SymmetrySet` (the scorer's)
        self.symmetry_sets: dict[str, SymmetrySet] = {}

    # ------------------------------------------------------------------ what a subclass provides
    def _read(self, split: str) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def _dataset(self, records: Any, indices: np.ndarray) -> Dataset:  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------------------ shared
    def records(self, split: str) -> Any:
        """``split``'s records, read once; their symmetry sets join :attr:`symmetry_sets`."""
        if split not in self._read_splits:
            r = self._read(split)
            self._read_splits[split] = r
            for s, S in r.symmetries.items():
                self.symmetry_sets.setdefault(s, SymmetrySet.from_transforms(S, name=f"{s} ({split} file)"))
        return self._read_splits[split]

    def _of_shape(self, records: Any, shape: str) -> np.ndarray:
        return np.flatnonzero(records.label == self.labels.index(shape))

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit", "validate") and self.train is None:
            r = self.records("train")
            train, val = [], []
            for s in self.shapes:
                idx = self._of_shape(r, s)
                n_val = min(
                    max(1, round(self.val_fraction * len(idx))),
                    self.max_val // len(self.shapes),
                    len(idx) - 1,
                )
                if n_val < 1:
                    raise OfficialDataError(
                        f"{r.source}: one {s} training record: nothing to hold out for validation"
                    )
                train.append(idx[:-n_val])
                val.append(idx[-n_val:])
            self.train = self._dataset(r, np.concatenate(train))
            self.val = self._dataset(r, np.concatenate(val))
        if stage in (None, "fit", "validate", "test", "predict") and self.test is None:
            r = self.records("test")
            keep = [self._of_shape(r, s) for s in self.shapes]
            if self.n_per_shape_test is not None:
                keep = [k[: self.n_per_shape_test] for k in keep]
            self.test = self._dataset(r, np.concatenate(keep))

    def symmetry_agreement(self) -> dict[str, float]:
        """Per SYMSOL I shape read, the largest angle (degrees) from a member of the file's symmetry set
        (after any frame conversion) to posediff's group (:mod:`posediff.symmetry`; cone / cylinder
        exactly, whatever grid the file uses): ~0 when the file's frames are posediff's."""
        out = {}
        for s, sset in self.symmetry_sets.items():
            if s in SHAPES:
                R = torch.from_numpy(sset.rotations_finite)
                identity = torch.eye(3, dtype=R.dtype).expand(len(R), 3, 3)
                out[s] = float(
                    torch.as_tensor(SymmetrySet.from_shape(s).min_angle_deg(R[:, None], identity)).max()
                )
        return out

    def train_dataloader(self) -> DataLoader:
        assert self.train is not None, "call setup('fit') first"
        return ResumableDataLoader(self.train, batch_size=self.batch_size, shuffle=True, seed=self.seed,
                                   drop_last=True, num_workers=self.num_workers, persistent_workers=False)  # fmt: skip

    def val_dataloader(self) -> DataLoader:
        assert self.val is not None, "call setup('fit') first"
        return eval_loader(self.val, batch_size=self.batch_size, num_workers=self.num_workers)

    def test_dataloader(self) -> DataLoader:
        assert self.test is not None, "call setup() first"
        return eval_loader(self.test, batch_size=self.batch_size, num_workers=self.num_workers)


__all__ = ["OfficialDataError", "OfficialDataModule", "padded_symmetries"]
