"""Tiny folders in the official layouts, rendered with posediff's own renderer (tests, and a reader's
smoke test on a machine without the real files; nothing is downloaded).

* :func:`make_symsol_fixture` — SYMSOL as the unpacked ``symsol_dataset.zip`` (``layout="zip"``) or a
  prepared ``symmetric_solids/1.0.0`` TensorFlow Datasets folder (``layout="tfds"``); the object at
  the scene centre, Haar rotations, the equivalents ``R·S_k`` of :mod:`posediff.symmetry` (cone and
  cylinder at 1°). SYMSOL II's marked shapes are stand-ins (``tetX`` → the plain tetrahedron,
  ``cylO`` → the cylinder, ``sphereX`` → the icosahedron) with the rendering rotation alone.
* :func:`make_symsolt_fixture` — SYMSOL-T as the paper's authors publish it (``<split>/annotations.gz``,
  ``<split>/<shape>/images/000000.png``): posediff's SYMSOL-T poses and renders, the records in
  their conventions (:func:`~.symsolt.to_theirs`: wxyz quaternions, their model frames, the
  equivalents in their group with the ground truth where theirs puts it: second for the polyhedra,
  181st for cone and cylinder).
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ...symmetry import SHAPES, SYMSOL_LABELS, SymmetrySet
from .tfrecord import encode_example, write_tfrecord

#: the plain shape rendered for each of SYMSOL II's marked shapes (no marked meshes in posediff)
STAND_INS = {"tetX": "tet", "cylO": "cyl", "sphereX": "icosa"}


def _png(rgb: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def _equivalents(shape: str, R: np.ndarray) -> np.ndarray:
    """``(N, K, 3, 3)``: ``R[i]·S_k`` over the shape's symmetries, the rendering rotation first."""
    if shape in STAND_INS:
        return R[:, None].astype(np.float32)
    S = SymmetrySet.from_shape(shape).rotations(step_deg=1.0)
    return np.einsum("nij,kjl->nkil", R, S).astype(np.float32)


def make_symsol_fixture(
    out: str | Path,
    *,
    layout: str = "zip",
    n_per_shape: int = 2,
    shapes: Sequence[str] = SYMSOL_LABELS,
    image_size: int = 32,
    seed: int = 0,
) -> Path:
    """Write ``n_per_shape`` images per shape and split into ``out`` (module docstring); returns the
    folder to give as ``data.root``."""
    from ..symsol.poses import haar_rotations
    from ..symsol.render import SCENE_DISTANCE, SymsolRenderer

    if layout not in ("zip", "tfds"):
        raise ValueError(f"unknown layout {layout!r}; choose zip or tfds")
    out = Path(out)
    renderer = SymsolRenderer(image_size)
    rng = np.random.default_rng(seed)
    t = np.array([0.0, 0.0, SCENE_DISTANCE])
    try:
        splits = {}
        for split in ("train", "test"):
            per_shape = {}
            for shape in shapes:
                R = haar_rotations(rng, n_per_shape)
                images = [
                    _png(renderer(STAND_INS.get(shape, shape), R[i], t).rgb) for i in range(n_per_shape)
                ]
                per_shape[shape] = (images, _equivalents(shape, R))
            splits[split] = per_shape
    finally:
        renderer.close()
    if layout == "zip":
        for split, per_shape in splits.items():
            images_dir = out / split / "images"
            images_dir.mkdir(parents=True, exist_ok=True)
            for shape, (images, _) in per_shape.items():
                for i, png in enumerate(images):
                    (images_dir / f"{shape}_{i:05d}.png").write_bytes(png)
            np.savez(out / split / "rotations.npz", **{s: eq for s, (_, eq) in per_shape.items()})
        return out
    folder = out / "symmetric_solids" / "1.0.0"
    folder.mkdir(parents=True, exist_ok=True)
    lengths = {}
    for split, per_shape in splits.items():
        records = [
            encode_example(
                {
                    "image": png,
                    "label_shape": np.array([SYMSOL_LABELS.index(shape)]),
                    "rotation": eq[i, 0].reshape(-1),
                    "rotations_equivalent": eq[i].reshape(-1),
                }
            )
            for shape, (images, eq) in per_shape.items()
            for i, png in enumerate(images)
        ]
        order = rng.permutation(len(records))  # tfds shuffles the shapes together
        records = [records[k] for k in order]
        half = (len(records) + 1) // 2
        for k, chunk in enumerate((records[:half], records[half:])):
            write_tfrecord(folder / f"symmetric_solids-{split}.tfrecord-{k:05d}-of-00002", chunk)
        lengths[split] = [half, len(records) - half]
    info = {
        "name": "symmetric_solids",
        "version": "1.0.0",
        "splits": [{"name": s, "shardLengths": [str(n) for n in v]} for s, v in lengths.items()],
    }
    (folder / "dataset_info.json").write_text(json.dumps(info, indent=2) + "\n")
    return folder


def make_symsolt_fixture(
    out: str | Path,
    *,
    n_per_shape: int = 2,
    shapes: Sequence[str] = SHAPES,
    image_size: int = 64,
    seed: int = 0,
) -> Path:
    """Write ``n_per_shape`` records per shape and split into ``out/train-N`` and ``out/test-N``
    (module docstring); returns ``out``, the folder to give as ``data.root``."""
    import gzip
    import pickle

    from ..symsol.poses import haar_rotations, scene_translations
    from ..symsol.render import SCENE_DISTANCE, SymsolRenderer
    from .symsolt import matrix_to_quaternion_wxyz, model_frame, to_theirs

    out = Path(out)
    renderer = SymsolRenderer(image_size)
    rng = np.random.default_rng(seed)
    try:
        for split in ("train", "test"):
            folder = out / f"{split}-{n_per_shape * len(shapes)}"
            merged = []
            for shape in shapes:
                (folder / shape / "images").mkdir(parents=True, exist_ok=True)
                R = haar_rotations(rng, n_per_shape)
                t = scene_translations(rng, n_per_shape, "uniform")
                C = model_frame(shape)[0]
                S = C @ SymmetrySet.from_shape(shape).rotations(step_deg=1.0) @ C.T  # their group
                at = 1 if len(S) < 100 else 180  # where their lists hold the ground truth
                S = np.roll(S, at, axis=0)
                records = []
                for i in range(n_per_shape):
                    img = renderer(shape, R[i], t[i] + np.array([0.0, 0.0, SCENE_DISTANCE])).rgb
                    name = f"images/{i:06d}.png"
                    (folder / shape / name).write_bytes(_png(img))
                    (folder / shape / f"images/{i:06d}_color.png").write_bytes(_png(img))
                    R_t, t_t = to_theirs(shape, R[i], t[i])
                    eq = matrix_to_quaternion_wxyz(R_t @ S)
                    records.append(
                        {
                            "image_id": i,
                            "image": name,
                            "image_color": f"images/{i:06d}_color.png",
                            "points": "points.ply",
                            "rotation": matrix_to_quaternion_wxyz(R_t).tolist(),
                            "rotations_equivalent": eq.reshape(-1).tolist(),
                            "translation": t_t.tolist(),
                            "num_equivalents": len(S),
                            "label_shape": SHAPES.index(shape),
                        }
                    )
                (folder / shape / "annotations.gz").write_bytes(gzip.compress(pickle.dumps(records)))
                for r in records:
                    merged.append({**r, **{k: f"{shape}/{r[k]}" for k in ("image", "image_color", "points")}})
            (folder / "annotations.gz").write_bytes(gzip.compress(pickle.dumps(merged)))
    finally:
        renderer.close()
    return out


__all__ = ["STAND_INS", "make_symsol_fixture", "make_symsolt_fixture"]
