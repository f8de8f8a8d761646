"""The paper authors' SYMSOL-T files (Hsiao et al., CVPR 2024), read as posediff's SYMSOL-T.

Their layout (``data=symsolt_official``, ``data.root=`` the folder holding one sub-folder per split,
``train-45k`` and ``test-5k`` as released; any ``train*`` / ``test*`` folder with an
``annotations.gz``)::

    <split>/annotations.gz          gzipped pickle: a list of plain dicts, every shape
    <split>/<shape>/images/000000.png, 000000_color.png, …   224 × 224 RGB, black background
    <split>/<shape>/points.ply      1024 surface points (not needed here)

A record: ``image`` / ``image_color`` (paths relative to the split folder), ``rotation`` (a wxyz
quaternion), ``rotations_equivalent`` (``num_equivalents`` × 4 wxyz, the ground truth among them),
``translation`` (3), ``num_equivalents``, ``label_shape`` (0–4: tet, cube, icosa, cone, cyl),
``image_id``, ``points``. ``annotations.gz`` is read by :func:`~.unpickle.load_plain_pickle`, which
refuses every class and function: a file that names one is refused in one line and nothing runs.

Conventions, theirs → posediff's (``docs/conventions.md`` has the table): both cameras are OpenCV
(x right, y down, z forward) with a 60° field of view and the scene centre at
:data:`~posediff.data.symsol.SCENE_DISTANCE` on the optical axis, and both translations are the
object's from that centre, so the camera-frame pose is ``[R | t + (0, 0, SCENE_DISTANCE)]`` in both.
Their meshes are Open3D's (centred on the vertex mean) and posediff's are its own (centred on the
centre of mass), so a point ``p`` of posediff's model is ``C·p + o`` in theirs and

    R_posediff = R_theirs · C,    t_posediff = t_theirs + R_theirs · o,

with ``C``, ``o`` per shape (:func:`model_frame`): the cube and cylinder share posediff's frame; their
cone sits on its base (vertex mean h/362 above it; posediff's centre of mass is h/4 above it), so
``o = (0, 0, h/4 − h/362)``; their tetrahedron has a vertex on +z and their icosahedron the
vertices ``(±1, 0, ±φ)`` and cyclic, so ``C`` is the rotation taking posediff's vertex directions
onto theirs. The solids themselves are the same as posediff's renders since scene version 2
(their icosahedron's circumradius 2.663; posediff's scene 1 had 1.40): one table,
:func:`posediff.data.symsol.shapes.authors_frame`, serves both readers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ...lie import LieGroup
from ...symmetry import SHAPES
from ..symsol.datamodule import to_sample
from ..symsol.render import SCENE_DISTANCE, intrinsics
from ..symsol.shapes import authors_frame
from .base import OfficialDataError, OfficialDataModule, padded_symmetries
from .symsol import _symmetries_of, read_png
from .unpickle import UnsafePickleError, load_plain_pickle

ANNOTATIONS = "annotations.gz"
_KEYS = ("image", "rotation", "rotations_equivalent", "translation", "label_shape")


# ----------------------------------------------------------------------------- conventions
def quaternion_wxyz_to_matrix(q: Any) -> np.ndarray:
    """``(…, 4)`` wxyz quaternions (normalised here) → ``(…, 3, 3)`` rotation matrices (float64)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion_wxyz(R: Any) -> np.ndarray:
    """``(…, 3, 3)`` rotations → ``(…, 4)`` unit wxyz quaternions (w ≥ 0), the inverse of
    :func:`quaternion_wxyz_to_matrix` (Shepperd's method: the largest of 1 + trace, 1 + 2R_ii − trace)."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for n, m in enumerate(flat):
        tr = np.trace(m)
        cand = [1 + tr, 1 + 2 * m[0, 0] - tr, 1 + 2 * m[1, 1] - tr, 1 + 2 * m[2, 2] - tr]
        k = int(np.argmax(cand))
        s = math.sqrt(max(cand[k], 1e-300)) * 2
        if k == 0:
            q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
        else:
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
        q = np.asarray(q)
        out[n] = q * (1.0 if q[0] >= 0 else -1.0) / np.linalg.norm(q)
    return out.reshape(*R.shape[:-2], 4)


def model_frame(shape: str) -> tuple[np.ndarray, np.ndarray]:
    """``(C (3, 3), o (3,))`` with ``p_theirs = C·p_posediff + o`` for a point of ``shape``'s model:
    :func:`posediff.data.symsol.shapes.authors_frame`, the one table posediff's own renders use too."""
    if shape not in SHAPES:
        raise OfficialDataError(f"unknown SYMSOL-T shape {shape!r}; available: {', '.join(SHAPES)}")
    return authors_frame(shape)


def to_posediff(shape: str, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Their pose(s) ``R (…, 3, 3)``, ``t (…, 3)`` (scene translation) → posediff's (module docstring)."""
    C, o = model_frame(shape)
    return R @ C, t + R @ o


def to_theirs(shape: str, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`to_posediff`."""
    C, o = model_frame(shape)
    R_t = R @ C.T
    return R_t, t - R_t @ o


# ----------------------------------------------------------------------------- records
def _split_folder(root: Path, split: str) -> Path:
    cands = sorted(
        p for p in root.iterdir() if p.is_dir() and p.name.startswith(split) and (p / ANNOTATIONS).is_file()
    )
    if not cands:
        raise OfficialDataError(
            f"{root}: no {split}* folder with {ANNOTATIONS} (the authors' SYMSOL-T has train-45k/ and test-5k/)"
        )
    return cands[0]


class _Records:
    """One split's records, converted (module docstring)."""

    def __init__(self, folder: Path, shapes: Sequence[str], color: bool) -> None:
        path = folder / ANNOTATIONS
        try:
            records = load_plain_pickle(path)
        except UnsafePickleError as e:
            raise OfficialDataError(str(e)) from None
        if not isinstance(records, list):
            raise OfficialDataError(f"{path}: holds a {type(records).__name__}, expected a list of records")
        wanted = {SHAPES.index(s) for s in shapes}
        files, labels, Rs, ts, syms = [], [], [], [], {}
        for i, rec in enumerate(records):
            where = f"{path} record {i}"
            if not isinstance(rec, dict) or any(k not in rec for k in _KEYS):
                have = ", ".join(sorted(map(str, rec))) if isinstance(rec, dict) else type(rec).__name__
                raise OfficialDataError(f"{where}: needs {', '.join(_KEYS)}; has {have}")
            try:
                label = int(rec["label_shape"])
                q = np.asarray(rec["rotation"], dtype=np.float64).reshape(4)
                t = np.asarray(rec["translation"], dtype=np.float64).reshape(3)
                eq = np.asarray(rec["rotations_equivalent"], dtype=np.float64).reshape(-1, 4)
                image = str(rec["image_color" if color else "image"])
            except (TypeError, ValueError, KeyError):
                raise OfficialDataError(
                    f"{where}: rotation must be 4 numbers (wxyz), translation 3, rotations_equivalent 4·n, "
                    "label_shape an integer"
                ) from None
            if not 0 <= label < len(SHAPES):
                raise OfficialDataError(f"{where}: label_shape {label} is not one of 0..{len(SHAPES) - 1}")
            if label not in wanted:
                continue
            shape = SHAPES[label]
            R_t = quaternion_wxyz_to_matrix(q)
            R, t_p = to_posediff(shape, R_t, t)
            if shape not in syms:
                R_eq = quaternion_wxyz_to_matrix(eq) @ model_frame(shape)[0]
                # the ground truth's position in the list is theirs to choose: put it first
                k0 = int(np.argmax(np.einsum("kij,ij->k", R_eq, R)))
                R_eq = np.concatenate([R_eq[k0 : k0 + 1], np.delete(R_eq, k0, 0)])
                syms[shape] = _symmetries_of(R_eq[None], where)[0]
            f = folder / image
            files.append(f)
            labels.append(label)
            Rs.append(R)
            ts.append(t_p)
        missing = [s for s in shapes if s not in syms]
        if missing:
            raise OfficialDataError(
                f"{path}: no records of {', '.join(missing)} (set data.shapes to a subset)"
            )
        absent = next((f for f in files if not f.is_file()), None)
        if absent is not None:
            raise OfficialDataError(f"{absent}: missing (named by {path}); the folder is incomplete")
        order = np.lexsort((np.arange(len(labels)), np.asarray(labels)))
        self.path = path
        self.source = str(path)
        self.files = [files[k] for k in order]
        self.label = np.asarray(labels, dtype=np.int64)[order]
        self.rotation = np.stack(Rs)[order].astype(np.float32)
        self.translation = np.stack(ts)[order].astype(np.float32)
        self.symmetries = syms

    def __len__(self) -> int:
        return len(self.label)


class SymsoltOfficialDataset(Dataset):
    """Samples ``indices`` of a split as posediff's SYMSOL-T samples (plus ``symmetries`` / ``symmetries_mask``)."""

    def __init__(
        self, records: _Records, indices: np.ndarray, image_size: int, rotation_only: bool,
        sym: torch.Tensor, mask: torch.Tensor,
    ) -> None:  # fmt: skip
        self.records, self.indices, self.image_size = (
            records,
            np.asarray(indices, dtype=np.int64),
            int(image_size),
        )
        self.rotation_only, self.sym, self.mask = rotation_only, sym, mask
        self.K = intrinsics(self.image_size)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, n: int) -> dict[str, Any]:
        i = int(self.indices[n])
        r = self.records
        f = r.files[i]
        rgb = read_png(f, self.image_size, str(f))
        t_cam = r.translation[i].astype(np.float64) + np.array([0.0, 0.0, SCENE_DISTANCE])
        label = int(r.label[i])
        out = to_sample(rgb, r.rotation[i], t_cam, label, self.K, i, rotation_only=self.rotation_only)
        out["symmetries"], out["symmetries_mask"] = self.sym[label], self.mask[label]
        return out


class SymsoltOfficialDataModule(OfficialDataModule):
    """The authors' SYMSOL-T (module docstring); ``conf/data/symsolt_official.yaml``. Validation holds
    out the last ``val_fraction`` of each shape's training records (training skips them)."""

    labels = SHAPES
    dataset_name = "SYMSOL-T"

    def __init__(
        self,
        root: str | None = None,
        *,
        shapes: Sequence[str] = SHAPES,
        image_size: int = 224,
        color: bool = False,
        n_per_shape_test: int | None = None,
        batch_size: int = 16,
        num_workers: int = 0,
        group: LieGroup | str = "se3",
        val_fraction: float = 0.05,
        max_val: int = 1000,
        seed: int = 0,
    ) -> None:
        super().__init__(
            root,
            "the authors' SYMSOL-T folder (train-45k/, test-5k/)",
            shapes=shapes, image_size=image_size, n_per_shape_test=n_per_shape_test, batch_size=batch_size,
            num_workers=num_workers, group=group, val_fraction=val_fraction, max_val=max_val, seed=seed,
        )  # fmt: skip
        if not self.root.is_dir():
            raise OfficialDataError(
                f"{self.root}: no such folder — point data.root at the authors' SYMSOL-T folder holding "
                "train-45k/ and test-5k/ (docs/data.md, 'The benchmarks' own files')"
            )
        if self.group.name not in ("so3", "se3", "r3so3"):
            raise OfficialDataError(
                f"SYMSOL-T poses need a 3-D rotation group (so3, se3, r3so3), not {self.group.name!r}"
            )
        self.color = bool(color)
        self.rotation_only = self.group.matrix_dim == 3

    def _read(self, split: str) -> _Records:
        return _Records(_split_folder(self.root, split), self.shapes, self.color)

    def _dataset(self, records: _Records, indices: np.ndarray) -> SymsoltOfficialDataset:
        sym, mask = padded_symmetries(records.symmetries, SHAPES)
        return SymsoltOfficialDataset(records, indices, self.image_size, self.rotation_only, sym, mask)

    def describe(self) -> str:
        return f"the authors' SYMSOL-T ({self.root}): shapes {', '.join(self.shapes)}, {self.image_size} px"

    def prediction_input(self, index: int) -> dict[str, Any]:
        s = self.test_sample(index)
        K, offset = self.image_camera({"image_size": self.image_size})
        shape = SHAPES[int(s["shape"])]
        return {"image": s["image"], "gt_pose": s["pose"], "shape": shape, "K": K, "camera_offset": offset,
                "info": {"shape": shape}}  # fmt: skip

    @classmethod
    def image_camera(cls, data_config: Any) -> tuple[Any, Any]:
        """Their camera (the same as posediff's renderer's) at ``image_size``, and the scene centre."""
        return intrinsics(int(data_config["image_size"])), np.array([0.0, 0.0, SCENE_DISTANCE])


__all__ = [
    "SymsoltOfficialDataModule",
    "SymsoltOfficialDataset",
    "matrix_to_quaternion_wxyz",
    "model_frame",
    "quaternion_wxyz_to_matrix",
    "to_posediff",
    "to_theirs",
]
