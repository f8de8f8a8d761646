"""The official SYMSOL I / II files (Implicit-PDF, Murphy et al. 2021), read as posediff's SYMSOL.

Two layouts of the same data (``data=symsol_official``, ``data.root=`` either):

* **the unpacked ``symsol_dataset.zip``**: ``<root>/<split>/images/<shape>_<index>.png`` (224×224 RGB)
  and ``<root>/<split>/rotations.npz`` holding, per shape name, ``(N, K, 3, 3)``: ``[i, 0]`` the
  rendering rotation of image ``i`` and ``[i, :]`` its known equivalent rotations (12 / 24 / 60 for
  the polyhedra, the continuous symmetry at 1° for cone and cylinder, the rendering rotation alone
  for SYMSOL II's marked shapes);
* **a prepared TensorFlow Datasets folder** ``tensorflow_datasets/symmetric_solids/<version>``
  (``dataset_info.json`` and ``symmetric_solids-<split>.tfrecord-NNNNN-of-NNNNN`` shards), read without
  TensorFlow (:mod:`.tfrecord`): features ``image`` (PNG), ``label_shape`` (the index in
  :data:`~posediff.symmetry.SYMSOL_LABELS`), ``rotation`` (9 floats) and ``rotations_equivalent``
  (K × 9 floats).

Batches have the keys of posediff's own rotation-only SYMSOL (``image`` (3, H, W) in [0, 1],
``pose`` = ``rotation`` (3, 3), ``translation`` zeros, ``shape`` the index in ``SYMSOL_LABELS``,
``index``) plus ``symmetries`` / ``symmetries_mask``: the file's equivalents as object-frame
symmetries ``S_k = R_0ᵀ R_k`` (posediff's right action, ``docs/conventions.md``), padded to the largest
set, which the symmetry-aware losses use; :attr:`SymsolOfficialDataModule.symmetry_sets` holds the
same sets per shape for the scorer, so spread and coverage are measured against the file's
equivalents (the cone's and cylinder's at the file's 1° step). :meth:`~SymsolOfficialDataModule.symmetry_agreement`
compares them with :mod:`posediff.symmetry`'s exact groups for SYMSOL I.

Validation holds out the last ``val_fraction`` of each shape's training images (index order), which
training skips; the test split is never read in training.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ...lie import LieGroup
from ...symmetry import SHAPES, SYMSOL_LABELS
from .base import OfficialDataError, OfficialDataModule, padded_symmetries
from .tfrecord import TFRecordError, TFRecordFile, parse_example

SPLITS = ("train", "test")
_TFDS_NAME = "symmetric_solids"
_IMAGE = re.compile(r"^(?P<shape>[A-Za-z]+)_(?P<index>\d+)\.png$")


# ----------------------------------------------------------------------------- images
def read_png(data: bytes | Path, size: int | None, where: str) -> np.ndarray:
    """A PNG (bytes or a file) as ``(size, size, 3)`` uint8 RGB (resized by nearest-neighbour
    sampling when ``size`` differs; ``None``: as stored); a damaged or truncated file → one line naming it.

    Nearest, not a smoothing filter: the renders are point-sampled (one ray a pixel, as the authors'
    Open3D and posediff's SYMSOL-T), and point-sampling them again keeps the object's apparent size —
    the depth cue — unbiased (the authors' 224 px images at 128 px: log-area bias −0.0001, std 0.003
    against posediff's own 128 px renders of the same poses; bilinear +0.056, 0.016; box +0.024, 0.007)."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data) if isinstance(data, bytes) else data) as im:
            im.load()
            rgb = im.convert("RGB")
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        raise OfficialDataError(f"{where}: not a readable image ({e})") from None
    if size is not None and rgb.size != (size, size):
        rgb = rgb.resize((size, size), Image.Resampling.NEAREST)
    return np.asarray(rgb, dtype=np.uint8)


def decode_png(data: bytes | Path, size: int | None, where: str) -> torch.Tensor:
    """:func:`read_png` as ``(3, size, size)`` float32 in [0, 1]."""
    arr = read_png(data, size, where)
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1))).float().div_(255.0)


# ----------------------------------------------------------------------------- records
@dataclass(frozen=True)
class _Split:
    """One split's records: ``label`` (N,) index in SYMSOL_LABELS, ``rotation`` (N, 3, 3) float32, and
    how to fetch image ``i`` (``files[i]`` a path, or ``(shard, record)`` pairs into ``shards``)."""

    label: np.ndarray
    rotation: np.ndarray
    files: list[Path] | None
    shards: list[TFRecordFile] | None
    where: np.ndarray | None  # (N, 2) shard, record
    symmetries: dict[str, np.ndarray]  # shape → (K, 3, 3) object-frame symmetries (identity first)
    source: str

    def __len__(self) -> int:
        return len(self.label)


def _consistent_right_set(eq: np.ndarray) -> np.ndarray | None:
    """``R_0ᵀ R_k`` of image 0 if every image's ``R_0ᵀ R_k`` is the same set (each member within 0.1°
    of one of image 0's), else ``None``."""
    S = np.einsum("kji,kjl->kil", np.broadcast_to(eq[0, :1], eq[0].shape), eq[0])
    for i in range(1, len(eq)):
        Si = np.einsum("kji,kjl->kil", np.broadcast_to(eq[i, :1], eq[i].shape), eq[i])
        if np.einsum("aij,bij->ab", Si, S).max(1).min() < 1.0 + 2.0 * np.cos(np.radians(0.1)):
            return None
    return S


def _symmetries_of(equivalents: np.ndarray, where: str, check: int = 8) -> tuple[np.ndarray, bool]:
    """The object-frame symmetry set ``S_k = R_0ᵀ R_k`` of a shape's ``(N, K, 3, 3)`` equivalents
    (from the first ``check`` images), and whether the file's rotations must be transposed to be
    posediff's object → camera rotations: equivalents ``R·S_k`` (a right action) are read as they
    are; equivalents ``S_k·R`` (the file storing camera → object rotations) are transposed. Neither
    (or one image only, which cannot tell) → read as they are when one image, else refused."""
    eq = np.asarray(equivalents[:check], dtype=np.float64)
    S = _consistent_right_set(eq)
    if S is not None:
        return S.astype(np.float32), False
    S = _consistent_right_set(eq.swapaxes(-1, -2))
    if S is not None:
        return S.astype(np.float32), True
    raise OfficialDataError(
        f"{where}: the equivalent rotations are not one symmetry set (expected [i, k] = [i, 0]·S_k, or "
        "S_k·[i, 0], for one set S)"
    )


def _read_npz(path: Path, shapes: Sequence[str]) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise OfficialDataError(
            f"{path}: missing (the unpacked symsol_dataset.zip has <split>/rotations.npz)"
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [s for s in shapes if s not in z.files]
            if missing:
                raise OfficialDataError(
                    f"{path}: no rotations for {', '.join(missing)} (it holds {', '.join(z.files) or 'nothing'}; "
                    "set data.shapes to a subset)"
                )
            return {s: z[s] for s in shapes}
    except OfficialDataError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise OfficialDataError(f"{path}: not a readable .npz ({type(e).__name__}: {e})") from None


def _zip_split(root: Path, split: str, shapes: Sequence[str]) -> _Split:
    """``<root>/<split>/images`` and ``rotations.npz`` (module docstring)."""
    folder = root / split
    images = folder / "images"
    if not images.is_dir():
        raise OfficialDataError(f"{images}: missing (the unpacked symsol_dataset.zip has {split}/images/)")
    rotations = _read_npz(folder / "rotations.npz", shapes)
    by_shape: dict[str, dict[int, Path]] = {s: {} for s in shapes}
    with os.scandir(images) as it:
        for entry in it:
            m = _IMAGE.match(entry.name)
            if m and m["shape"] in by_shape:
                by_shape[m["shape"]][int(m["index"])] = Path(entry.path)
    labels, rots, files, syms = [], [], [], {}
    for s in shapes:
        arr = rotations[s]
        if arr.ndim != 4 or arr.shape[-2:] != (3, 3) or arr.shape[1] < 1:
            raise OfficialDataError(
                f"{folder / 'rotations.npz'}: {s!r} has shape {arr.shape}, expected (N, K, 3, 3)"
            )
        n = len(arr)
        have = by_shape[s]
        if len(have) != n or (n and (min(have) != 0 or max(have) != n - 1)):
            raise OfficialDataError(
                f"{images}: {len(have)} {s} images but {n} rotations in rotations.npz "
                f"(expected {s}_<index>.png for every index 0 … {n - 1})"
            )
        syms[s], transposed = _symmetries_of(arr, f"{folder / 'rotations.npz'} [{s}]")
        labels.append(np.full(n, SYMSOL_LABELS.index(s), dtype=np.int64))
        R0 = np.asarray(arr[:, 0], dtype=np.float32)
        rots.append(R0.swapaxes(-1, -2) if transposed else R0)
        files += [have[i] for i in range(n)]
    return _Split(np.concatenate(labels), np.concatenate(rots), files, None, None, syms, str(folder))


def find_tfds_folder(root: Path) -> Path | None:
    """The prepared ``symmetric_solids/<version>`` folder at or under ``root`` (``root`` itself, its
    ``symmetric_solids/<version>``, or ``<version>``), the newest version first; ``None``: none."""
    if (root / "dataset_info.json").is_file():
        return root
    for base in (root / _TFDS_NAME, root):
        if base.is_dir():
            versions = sorted(
                (p for p in base.iterdir() if (p / "dataset_info.json").is_file()), reverse=True
            )
            if versions:
                return versions[0]
    return None


def _tfds_split(folder: Path, split: str, shapes: Sequence[str]) -> _Split:
    """The ``split`` shards of a prepared ``symmetric_solids`` folder (module docstring)."""
    try:
        info = json.loads((folder / "dataset_info.json").read_text())
    except (OSError, ValueError) as e:
        raise OfficialDataError(f"{folder / 'dataset_info.json'}: not readable JSON ({e})") from None
    name = info.get("name", _TFDS_NAME)
    paths = sorted(folder.glob(f"{name}-{split}.tfrecord-*"))
    if not paths:
        raise OfficialDataError(
            f"{folder}: no {name}-{split}.tfrecord-* shards (a prepared tfds folder has them)"
        )
    try:
        shards = [TFRecordFile(p) for p in paths]
    except TFRecordError as e:
        raise OfficialDataError(str(e)) from None
    wanted = {SYMSOL_LABELS.index(s) for s in shapes}
    labels, rots, where, first = [], [], [], {}
    for k, shard in enumerate(shards):
        for j in range(len(shard)):
            rec = f"{shard.path} record {j}"
            try:
                ex = parse_example(shard.read(j))
            except TFRecordError as e:
                raise OfficialDataError(f"{rec}: {e}") from None
            try:
                label = int(np.asarray(ex["label_shape"]).reshape(-1)[0])
                R = np.asarray(ex["rotation"], dtype=np.float32).reshape(3, 3)
            except (KeyError, IndexError, ValueError, TypeError):
                raise OfficialDataError(
                    f"{rec}: not a symmetric_solids example (needs label_shape, rotation, "
                    f"rotations_equivalent, image; has {', '.join(sorted(ex)) or 'nothing'})"
                ) from None
            if not 0 <= label < len(SYMSOL_LABELS):
                raise OfficialDataError(
                    f"{rec}: label_shape {label} is not one of 0..{len(SYMSOL_LABELS) - 1}"
                )
            if label not in wanted:
                continue
            shape = SYMSOL_LABELS[label]
            if len(first.setdefault(shape, [])) < 8:  # the first images' equivalents: the set, and its side
                eq = np.asarray(ex.get("rotations_equivalent", np.zeros(0)), dtype=np.float32)
                if eq.size == 0 or eq.size % 9 or (first[shape] and eq.size != first[shape][0].size):
                    raise OfficialDataError(
                        f"{rec}: rotations_equivalent has {eq.size} values, not K × 9 as the others"
                    )
                first[shape].append(eq.reshape(-1, 3, 3))
            labels.append(label)
            rots.append(R)
            where.append((k, j))
    missing = [s for s in shapes if s not in first]
    if missing:
        raise OfficialDataError(
            f"{folder}: the {split} shards hold no {', '.join(missing)} (set data.shapes to a subset)"
        )
    syms = {}
    R_all, lab = np.stack(rots), np.asarray(labels)
    for shape, eqs in first.items():
        syms[shape], transposed = _symmetries_of(np.stack(eqs), f"{folder} [{shape}]")
        if transposed:
            sel = lab == SYMSOL_LABELS.index(shape)
            R_all[sel] = R_all[sel].swapaxes(-1, -2)
    order = np.lexsort((np.arange(len(labels)), np.asarray(labels)))  # by shape, file order within
    return _Split(
        np.asarray(labels, dtype=np.int64)[order],
        R_all[order],
        None,
        shards,
        np.asarray(where, dtype=np.int64).reshape(-1, 2)[order],
        syms,
        str(folder),
    )


def layout(root: Path) -> str:
    """``"zip"`` or ``"tfds"``: which layout ``root`` holds; neither → one line naming what was looked for."""
    if not root.exists():
        raise OfficialDataError(
            f"{root}: no such folder — point data.root at the unpacked symsol_dataset.zip or at a prepared "
            "tensorflow_datasets/symmetric_solids/1.0.0 folder (docs/data.md, 'The benchmarks' own files')"
        )
    if (root / "train" / "images").is_dir() or (root / "test" / "images").is_dir():
        return "zip"
    if find_tfds_folder(root) is not None:
        return "tfds"
    raise OfficialDataError(
        f"{root}: neither official SYMSOL layout (expected train/ and test/ with images/ and rotations.npz, "
        "or a tfds symmetric_solids/<version> folder with dataset_info.json)"
    )


# ----------------------------------------------------------------------------- dataset
class SymsolOfficialDataset(Dataset):
    """Map-style samples ``indices`` of a split (module docstring); images decoded on access."""

    def __init__(
        self, split: _Split, indices: np.ndarray, image_size: int, sym: torch.Tensor, mask: torch.Tensor
    ) -> None:
        self.split, self.indices, self.image_size = (
            split,
            np.asarray(indices, dtype=np.int64),
            int(image_size),
        )
        self.sym, self.mask = sym, mask  # (labels, K, 3, 3), (labels, K)

    def __len__(self) -> int:
        return len(self.indices)

    def _image(self, i: int) -> torch.Tensor:
        sp = self.split
        if sp.files is not None:
            return decode_png(sp.files[i], self.image_size, str(sp.files[i]))
        assert sp.shards is not None and sp.where is not None
        k, j = (int(x) for x in sp.where[i])
        where = f"{sp.shards[k].path} record {j}"
        try:
            ex = parse_example(sp.shards[k].read(j))
        except TFRecordError as e:
            raise OfficialDataError(f"{where}: {e}") from None
        image = ex.get("image")
        if not isinstance(image, list) or not image:
            raise OfficialDataError(f"{where}: no encoded image")
        return decode_png(image[0], self.image_size, where)

    def __getitem__(self, n: int) -> dict[str, torch.Tensor]:
        i = int(self.indices[n])
        R = torch.from_numpy(np.array(self.split.rotation[i], dtype=np.float32))
        label = int(self.split.label[i])
        return {
            "image": self._image(i),
            "pose": R,
            "rotation": R,
            "translation": torch.zeros(3),
            "shape": torch.tensor(label, dtype=torch.int64),
            "index": torch.tensor(i, dtype=torch.int64),
            "symmetries": self.sym[label],
            "symmetries_mask": self.mask[label],
        }


class SymsolOfficialDataModule(OfficialDataModule):
    """The official SYMSOL files (module docstring); ``conf/data/symsol_official.yaml``."""

    labels = SYMSOL_LABELS
    dataset_name = "SYMSOL"
    #: evaluations report the ground truth's log density by default (SYMSOL's ranking metric)
    log_likelihood_default = True

    def __init__(
        self,
        root: str | None = None,
        *,
        shapes: Sequence[str] = SHAPES,
        image_size: int = 224,
        n_per_shape_test: int | None = None,
        batch_size: int = 32,
        num_workers: int = 0,
        group: LieGroup | str = "so3",
        val_fraction: float = 0.05,
        max_val: int = 1000,
        seed: int = 0,
    ) -> None:
        super().__init__(
            root,
            "the unpacked symsol_dataset.zip or a prepared tensorflow_datasets/symmetric_solids/1.0.0 folder",
            shapes=shapes, image_size=image_size, n_per_shape_test=n_per_shape_test, batch_size=batch_size,
            num_workers=num_workers, group=group, val_fraction=val_fraction, max_val=max_val, seed=seed,
        )  # fmt: skip
        if self.group.name != "so3":
            raise OfficialDataError(
                f"SYMSOL images carry rotations only: use group=so3 (got group={self.group.name})"
            )
        self.layout = layout(self.root)

    def _read(self, split: str) -> _Split:
        if self.layout == "zip":
            return _zip_split(self.root, split, self.shapes)
        folder = find_tfds_folder(self.root)
        assert folder is not None
        return _tfds_split(folder, split, self.shapes)

    def _dataset(self, records: _Split, indices: np.ndarray) -> SymsolOfficialDataset:
        return SymsolOfficialDataset(
            records, indices, self.image_size, *padded_symmetries(records.symmetries, SYMSOL_LABELS)
        )

    def describe(self) -> str:
        what = "unpacked symsol_dataset.zip" if self.layout == "zip" else "tfds symmetric_solids"
        line = (
            f"official SYMSOL ({what} in {self.root}): shapes {', '.join(self.shapes)}, {self.image_size} px"
        )
        off = {s: a for s, a in self.symmetry_agreement().items() if a > 0.5}
        if off:  # the scorer uses the file's sets; posediff's own shape-specific heads assume its frames
            worst = ", ".join(f"{s} {a:.1f}°" for s, a in off.items())
            line += (f"; the file's symmetries are not posediff's groups in posediff's frames ({worst}): "
                     "encoder.rotation_head=invariant and module.symmetry_fold assume posediff's")  # fmt: skip
        return line

    def prediction_input(self, index: int) -> dict[str, Any]:
        s = self.test_sample(index)
        shape = SYMSOL_LABELS[int(s["shape"])]
        sset = self.symmetry_sets.get(shape)
        gt = None
        if sset is not None:
            gt = (s["rotation"].double() @ torch.from_numpy(sset.rotations_finite)).numpy()
        return {
            "image": s["image"],
            "gt_pose": s["pose"],
            "shape": shape,
            "gt_rotations": gt,
            "info": {"shape": shape},
        }


__all__ = [
    "OfficialDataError",
    "SymsolOfficialDataModule",
    "SymsolOfficialDataset",
    "decode_png",
    "find_tfds_folder",
    "layout",
    "read_png",
]
