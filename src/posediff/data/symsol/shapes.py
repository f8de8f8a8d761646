"""The five SYMSOL shapes as meshes, their symmetry groups and equivalent poses.

The solids are the paper authors' (their SYMSOL-T synthesis builds them with Open3D,
``../shared/docs/reference-implementation.md`` §7.5: ``shape_size`` 3.5), placed in the object frames
of :mod:`posediff.symmetry`, where the symmetry groups are exact:

========  =========================================================================================
``tet``   regular tetrahedron, circumradius 3.5 / 1.3 = 2.692, vertices ∝ (1,1,1), (1,−1,−1), …
``cube``  axis-aligned cube, edge 3.5
``icosa`` regular icosahedron with vertices (0, ±r, ±rφ) and cyclic, r = 3.5 / 2.5 = 1.4, so its
          circumradius is 1.4·√(1 + φ²) = 2.663 (Open3D's ``create_icosahedron(radius=1.4)`` scales
          the unnormalised vertices; posediff's scene before version 2 normalised them: 1.4)
``cone``  radius 1.75, height 3.5, axis +z towards the apex, 360 sections (one every 1°)
``cyl``   radius 1.75, height 3.5, axis z, 360 sections
========  =========================================================================================

Every mesh is centred on its volume centroid (for the cone that is a quarter of the height above
the base; the authors' Open3D cone is centred on its vertex mean, i.e. almost on the base plane),
so the pose translation is the object's centre and its projection is the centre of the silhouette.

**The authors' frames** (:func:`authors_frame`, the one table both posediff's renders and the reader
of the authors' files use): a point ``p`` of posediff's model is ``C·p + o`` in theirs. Their
tetrahedron has a vertex on +z and their icosahedron the vertices ``(±1, 0, ±φ)`` and cyclic, so
``C`` is the rotation taking posediff's vertex directions onto theirs; their cone sits on its base
(vertex mean h/362 above it, posediff's centre of mass h/4 above it), so ``o = (0, 0, h/4 − h/362)``;
cube and cylinder share posediff's frame. A pose ``[R_theirs | t_theirs]`` is
``[R_theirs·C | t_theirs + R_theirs·o]`` in posediff's frames, and posediff's SYMSOL-T draws its
translations for the authors' origin (uniform in their cube), so both serve one distribution.

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
    if shape == "tet":  # Open3D's create_tetrahedron(radius): the circumradius
        mesh = _hull(_posediff_vertex_directions("tet") * (s / 1.3))
    elif shape == "cube":
        mesh = trimesh.creation.box(extents=(s, s, s))
    elif shape == "icosa":  # Open3D's create_icosahedron(radius): radius times (0, ±1, ±φ), unnormalised
        mesh = _hull(_posediff_vertex_directions("icosa") * (s / 2.5) * math.sqrt(1.0 + GOLDEN_RATIO**2))
    elif shape == "cone":
        mesh = trimesh.creation.cone(radius=s / 2, height=s, sections=ROUND_SECTIONS)
    else:  # cyl
        mesh = trimesh.creation.cylinder(radius=s / 2, height=s, sections=ROUND_SECTIONS)
    mesh.apply_translation(-mesh.center_mass)
    mesh.fix_normals()
    return mesh


def _their_vertex_directions(shape: str) -> np.ndarray:
    """Unit vertex directions of the authors' Open3D tetrahedron / icosahedron (Open3D's
    ``create_tetrahedron`` / ``create_icosahedron``)."""
    if shape == "tet":
        v = np.array([(math.sqrt(8 / 9), 0, -1 / 3), (-math.sqrt(2 / 9), math.sqrt(2 / 3), -1 / 3),
                      (-math.sqrt(2 / 9), -math.sqrt(2 / 3), -1 / 3), (0, 0, 1)])  # fmt: skip
    else:
        p = GOLDEN_RATIO
        base = [(a, 0.0, b * p) for a in (-1, 1) for b in (-1, 1)]
        v = np.array([c[-k:] + c[:-k] if k else c for c in base for k in range(3)], dtype=np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _posediff_vertex_directions(shape: str) -> np.ndarray:
    if shape == "tet":
        v = np.array([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)], dtype=np.float64)
    else:
        p = GOLDEN_RATIO
        base = [(0.0, a, b * p) for a in (-1, 1) for b in (-1, 1)]
        v = np.array([c[k:] + c[:k] for c in base for k in range(3)], dtype=np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _frame(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The right-handed orthonormal frame with first axis ``x`` and second in the ``x``, ``y`` plane."""
    n = np.cross(x, y) / np.linalg.norm(np.cross(x, y))
    return np.stack([x, np.cross(n, x), n], 1)


def _rotation_onto(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """A rotation C with ``C·src`` = ``dst`` as sets of unit vectors (the first found: any two
    differ by a symmetry of the solid)."""
    a = src[0]
    b = next(v for v in src[1:] if abs(v @ a) < 0.999)
    for i in range(len(dst)):
        for j in range(len(dst)):
            if i == j or abs(dst[i] @ dst[j] - a @ b) > 1e-9:
                continue
            C = _frame(dst[i], dst[j]) @ _frame(a, b).T
            if np.abs((src @ C.T) @ dst.T).max(1).min() > 1 - 1e-9:
                return C
    raise AssertionError("no rotation maps the vertex sets onto each other")  # pragma: no cover


@functools.cache
def _authors_frame(shape: str) -> tuple[np.ndarray, np.ndarray]:
    C, o = np.eye(3), np.zeros(3)
    if shape in ("tet", "icosa"):
        C = _rotation_onto(_posediff_vertex_directions(shape), _their_vertex_directions(shape))
    elif shape == "cone":
        o = np.array([0.0, 0.0, SHAPE_SIZE / 4.0 - SHAPE_SIZE / (ROUND_SECTIONS + 2)])
    C.setflags(write=False)
    o.setflags(write=False)
    return C, o


def authors_frame(shape: str | int) -> tuple[np.ndarray, np.ndarray]:
    """``(C (3, 3), o (3,))`` with ``p_theirs = C·p + o`` for a point ``p`` of posediff's model of
    ``shape`` (module docstring); read-only arrays."""
    return _authors_frame(shape_name(shape))


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
    "authors_frame",
    "make_mesh",
    "symmetries",
    "equivalent_poses",
]
