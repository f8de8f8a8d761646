"""Which poses a SYMSOL / SYMSOL-T split holds: deterministic in (seed, split, shape).

* ``symsol``: rotation only, the object at the scene centre (translation 0);
* ``symsolt``: Haar-random rotation and a scene-frame translation by ``variant`` — the paper's
  perspective variants (§5, "Uniform / Edge / Centered"; the authors' ``dist_type`` ``uniform`` /
  ``sign`` / ``zero``): ``uniform`` U[−1, 1]³, ``edge`` the 8 corners (±1, ±1, ±1) (the maximum
  distance from the centre), ``centered`` 0.

The variants draw the translation of the authors' model origin (their cone's is its vertex mean,
near the base: :func:`~posediff.data.symsol.shapes.authors_frame`), so posediff's SYMSOL-T has the
distribution of theirs; the pose served is posediff's (the centre of mass), ``t = t_theirs + R·Cᵀo``.
The camera-frame translation is the scene translation plus (0, 0, ``SCENE_DISTANCE``). Each
(seed, split, shape) has its own random stream (``numpy.random.SeedSequence``), so train and test
never share poses for one seed, and the samples of all shapes are interleaved in a seeded order
(so every shard of a dataset mixes the shapes).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...symmetry import SHAPES
from .render import SCENE_DISTANCE
from .shapes import SHAPE_IDS, authors_frame, shape_name

DATASETS: tuple[str, ...] = ("symsol", "symsolt")
VARIANTS: tuple[str, ...] = ("uniform", "edge", "centered")
_SPLIT_CODES = {"train": 0, "test": 1, "val": 2}


def default_variant(dataset: str) -> str:
    return "centered" if dataset == "symsol" else "uniform"


def check_spec(dataset: str, variant: str | None, split: str) -> str:
    """Validate the names (one-line errors listing the valid ones); returns the variant."""
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; available: {', '.join(DATASETS)}")
    if split not in _SPLIT_CODES:
        raise ValueError(f"unknown split {split!r}; available: {', '.join(_SPLIT_CODES)}")
    variant = variant or default_variant(dataset)
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; available: {', '.join(VARIANTS)}")
    if dataset == "symsol" and variant != "centered":
        raise ValueError(f"symsol has no translation, so no variant {variant!r} (use dataset=symsolt)")
    return variant


def haar_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` Haar-uniform rotations ``(n, 3, 3)`` float64 (normalised Gaussian quaternions)."""
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.empty((n, 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def scene_translations(rng: np.random.Generator, n: int, variant: str) -> np.ndarray:
    if variant == "uniform":
        return rng.uniform(-1.0, 1.0, (n, 3))
    if variant == "edge":
        return rng.choice(np.array([-1.0, 1.0]), size=(n, 3))
    return np.zeros((n, 3))


@dataclass(frozen=True)
class PoseSet:
    """``shape_id`` (N,) int64; ``R`` (N, 3, 3) and ``t`` (N, 3) camera-frame float64."""

    shape_id: np.ndarray
    R: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return int(self.shape_id.shape[0])

    def digest(self, start: int = 0, stop: int | None = None) -> str:
        """:func:`pose_digest` of the samples ``start:stop`` (all by default)."""
        sl = slice(start, stop)
        return pose_digest(self.shape_id[sl], self.R[sl], self.t[sl])


def pose_digest(shape_id: np.ndarray, R: np.ndarray, t: np.ndarray) -> str:
    """SHA-256 (hex) of the poses ``shape_id`` (n,), ``R`` (n, 3, 3), ``t`` (n, 3) as little-endian
    int64 / float64 bytes, in order: what a shard records of the poses it was rendered from, and
    what the reader recomputes from ``index.npz`` (equal arrays, equal digests)."""
    h = hashlib.sha256()
    for arr, dtype, shape in ((shape_id, "<i8", (-1,)), (R, "<f8", (-1, 3, 3)), (t, "<f8", (-1, 3))):
        a = np.ascontiguousarray(np.asarray(arr).astype(dtype, copy=False).reshape(shape))
        h.update(f"{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def sample_poses(
    dataset: str,
    variant: str | None,
    split: str,
    n_per_shape: int,
    seed: int,
    shapes: Sequence[str] = SHAPES,
) -> PoseSet:
    """The poses of a split, ``n_per_shape`` per shape, interleaved in a seeded order."""
    variant = check_spec(dataset, variant, split)
    if n_per_shape < 1:
        raise ValueError(f"n_per_shape must be at least 1, got {n_per_shape}")
    if not shapes:
        raise ValueError(f"no shapes given; available: {', '.join(SHAPES)}")
    names = [shape_name(s) for s in shapes]
    twice = sorted({s for s in names if names.count(s) > 1})
    if twice:
        raise ValueError(f"shapes lists {', '.join(twice)} more than once; give each shape once")
    ids, Rs, ts = [], [], []
    for shape in shapes:
        sid = SHAPE_IDS[shape_name(shape)]
        rng = np.random.default_rng(np.random.SeedSequence([seed, _SPLIT_CODES[split], sid]))
        R = haar_rotations(rng, n_per_shape)
        t = scene_translations(rng, n_per_shape, variant)
        if dataset == "symsolt":  # the authors' origin is what the variant places (module docstring)
            C, o = authors_frame(sid)
            t = t + R @ (C.T @ o)
        Rs.append(R)
        ts.append(t + np.array([0.0, 0.0, SCENE_DISTANCE]))
        ids.append(np.full(n_per_shape, sid, dtype=np.int64))
    order = np.random.default_rng(np.random.SeedSequence([seed, _SPLIT_CODES[split], 1000])).permutation(
        n_per_shape * len(ids)
    )
    return PoseSet(np.concatenate(ids)[order], np.concatenate(Rs)[order], np.concatenate(ts)[order])


__all__ = [
    "DATASETS",
    "VARIANTS",
    "PoseSet",
    "check_spec",
    "default_variant",
    "haar_rotations",
    "pose_digest",
    "sample_poses",
]
