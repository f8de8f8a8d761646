"""The five SYMSOL shapes as meshes, their symmetry groups and equivalent poses.

Geometry follows the authors' SYMSOL-T synthesis (``../shared/docs/reference-implementation.md``
§7.5: shapes 3.5 units across) in the object frames of :mod:`posediff.symmetry`, where the symmetry
groups are exact:

========  =========================================================================================
``tet``   regular tetrahedron, circumradius 3.5 / 1.3 = 2.692, vertices ∝ (1,1,1), (1,−1,−1), …
``cube``  axis-aligned cube, edge 3.5
``icosa`` regular icosahedron, circumradius 3.5 / 2.5 = 1.4 (smaller than the others, as the authors')
``cone``  radius 1.75, height 3.5, axis +z towards the apex, 360 sections (one every 1°)
``cyl``   radius 1.75, height 3.5, axis z, 360 sections
========  =========================================================================================

Every mesh is centred on its volume centroid (for the cone that is a quarter of the height above
the base; the authors' Open3D cone is centred on its vertex mean, i.e. almost on the base plane),
so the pose translation is the object's centre and its projection is the centre of the silhouette.

Symmetry acts on the right, translation unchanged: the poses ``[R | t]`` and ``[R·S | t]`` render
to the same image for every ``S`` in :func:`symmetries` (tested by rendering).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from torch import Tensor

from ...symmetry import GOLDEN_RATIO, SHAPES, is_continuous, shape_name, symmetry_group

#: Integer id of each shape (its index in :data:`posediff.symmetry.SHAPES`), as stored in datasets.
SHAPE_IDS: dict[str, int] = {s: i for i, s in enumerate(SHAPES)}

#: Object size (units): the authors' ``shape_size``.
SHAPE_SIZE = 3.5
#: Sections of the cone and cylinder meshes: one vertex every 1°, so the 1° symmetry grid maps
#: the mesh exactly onto itself.
ROUND_SECTIONS = 360


def _hull(vertices: np.ndarray):  # noqa: ANN202 — trimesh.Trimesh
    import trimesh

    return trimesh.convex.convex_hull(trimesh.PointCloud(vertices))


@functools.cache
def _mesh(shape: str):  # noqa: ANN202
    import trimesh

    s = SHAPE_SIZE
    if shape == "tet":
        v = np.array([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)], dtype=np.float64)
        mesh = _hull(v * (s / 1.3) / math.sqrt(3.0))
    elif shape == "cube":
        mesh = trimesh.creation.box(extents=(s, s, s))
    elif shape == "icosa":
        p = GOLDEN_RATIO
        base = [(0, a, b * p) for a in (-1, 1) for b in (-1, 1)]
        v = np.array([c[k:] + c[:k] for c in base for k in range(3)], dtype=np.float64)
        mesh = _hull(v * (s / 2.5) / math.sqrt(1.0 + p * p))
    elif shape == "cone":
        mesh = trimesh.creation.cone(radius=s / 2, height=s, sections=ROUND_SECTIONS)
    else:  # cyl
        mesh = trimesh.creation.cylinder(radius=s / 2, height=s, sections=ROUND_SECTIONS)
    mesh.apply_translation(-mesh.center_mass)
    mesh.fix_normals()
    return mesh


def make_mesh(shape: str | int):  # noqa: ANN201 — trimesh.Trimesh
    """A fresh ``trimesh.Trimesh`` of ``shape`` in its canonical object frame (module docstring)."""
    return _mesh(shape_name(shape)).copy()


@dataclasses.dataclass(frozen=True)
class Symmetry:
    """The rotational symmetry group of a shape.

    ``discrete`` ``(S, 3, 3)`` float64, identity first: the exact group for tet / cube / icosa
    (S = 12 / 24 / 60); for cone / cylinder the discretisation used in evaluation (rotations about
    z every ``step_deg``; the cylinder also composes them with the flip Rx(π): 360 and 720 at 1°).
    ``axis``: the continuous symmetry axis ((0, 0, 1)) or ``None``; ``flip``: whether rotations by π
    about every axis perpendicular to ``axis`` are symmetries too (the cylinder).
    """

    shape: str
    discrete: Tensor
    axis: tuple[float, float, float] | None
    flip: bool

    @property
    def continuous(self) -> bool:
        return self.axis is not None

    def __len__(self) -> int:
        return int(self.discrete.shape[0])


def symmetries(shape: str | int, step_deg: float = 1.0) -> Symmetry:
    """The symmetry group of ``shape`` (see :class:`Symmetry`); ``step_deg`` (dividing 360) sets
    the discretisation of the continuous groups."""
    name = shape_name(shape)
    group = symmetry_group(name, step_deg=step_deg)
    if not is_continuous(name):
        return Symmetry(name, group, None, False)
    return Symmetry(name, group, (0.0, 0.0, 1.0), name == "cyl")


def equivalent_poses(shape: str | int, pose: Tensor, step_deg: float = 1.0) -> Tensor:
    """The ground-truth poses that look identical to ``pose``: ``(…, 3, 3)`` rotations or
    ``(…, 4, 4)`` poses ``[R | t]`` → ``(…, S, 3, 3)`` / ``(…, S, 4, 4)`` with ``R·S`` and the same
    ``t``; the first is ``pose`` itself. Cone / cylinder: the ``step_deg`` discretisation."""
    G = symmetries(shape, step_deg).discrete.to(dtype=pose.dtype, device=pose.device)
    if pose.shape[-2:] == (3, 3):
        return pose.unsqueeze(-3) @ G
    if pose.shape[-2:] != (4, 4):
        raise ValueError(f"pose must be (…, 3, 3) or (…, 4, 4), got {tuple(pose.shape)}")
    out = pose.unsqueeze(-3).repeat_interleave(G.shape[0], dim=-3).clone()
    out[..., :3, :3] = pose[..., None, :3, :3] @ G
    return out


__all__ = [
    "SHAPE_IDS",
    "SHAPE_SIZE",
    "ROUND_SECTIONS",
    "Symmetry",
    "shape_name",
    "make_mesh",
    "symmetries",
    "equivalent_poses",
]
