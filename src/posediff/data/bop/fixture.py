"""A small synthetic dataset in the BOP layout (as T-LESS), made by the project for its tests.

:func:`make_bop_fixture` writes three objects (ids 1, 2, 3; T-LESS-like sizes, in mm) and three
splits, rendered with :class:`~posediff.data.bop.render.BopRenderer`::

    out/
      camera_primesense.json        T-LESS primesense intrinsics scaled to width x height
      models/, models_eval/         obj_000001.ply … (binary PLY with vertex normals) + models_info.json
      train_pbr/000000/ …           clutter over random backgrounds, rgb .jpg, own camera (cam_K)
      train_primesense/000001/ …    one scene per object (scene id = obj id), object alone on black
      test_primesense/000001/ …     objects close together on a table plane, occluding each other
      test_targets_bop19.json

Each scene folder holds ``rgb/``, ``depth/`` (uint16 PNG; mm = value * depth_scale, depth_scale
0.1), ``mask/`` and ``mask_visib/`` (uint8 0/255, ``{im_id:06d}_{gt_idx:06d}.png``),
``scene_gt.json``, ``scene_camera.json`` (``cam_K``, ``depth_scale`` and the optional
``cam_R_w2c``, ``cam_t_w2c``) and ``scene_gt_info.json``. Image ids run from 0 in each scene; the
instances of an image are listed by ascending ``obj_id`` (then placement order), the same
instances in every image of a scene (a static world seen from several cameras).

Objects (origin at the bounding-box centre):

1. a closed cylinder about z: continuous symmetry about z and the discrete flip Rx(π);
2. a box with three different edge lengths: discrete Rx(π), Ry(π), Rz(π);
3. an L-shaped bracket with an off-centre peg: no symmetry.

Facts of the layout: the full mask is the instance rendered alone (``depth > 0``); ``mask_visib``
is where its own depth is within :data:`~posediff.data.bop.render.VISIB_TOLERANCE_MM` of the scene
depth; ``bbox_*`` are ``[x, y, w, h]`` of those masks (``[-1, -1, -1, -1]`` when empty) — every
instance is kept wholly inside the image (cameras are re-drawn until its projected vertices are),
so ``bbox_obj`` is the box of the whole projected object, as BOP defines it. ``px_count_valid``
counts mask pixels with a non-zero depth PNG value; ``visib_fract = px_count_visib /
px_count_all`` (0 when the object has no pixel). The test targets follow the BOP19 rule: per test
image and object, ``inst_count`` is the number of instances with ``visib_fract >= 0.1``; an object
with none is left out. JSON keys are image ids as strings; floats are written exactly (the rendered
poses).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..._io import check_output_dir, make_output_dir, remove_own_dir, replace_dir
from .render import VISIB_TOLERANCE_MM, BopRenderer, RenderedScene

#: T-LESS primesense camera (720 x 540); :func:`camera` scales it to the fixture's image size.
TLESS_PRIMESENSE = {"width": 720, "height": 540, "fx": 1075.65, "fy": 1073.90, "cx": 373.06, "cy": 257.73}
#: Depth PNG unit (mm per value), as T-LESS primesense.
DEPTH_SCALE = 0.1
#: BOP19: instances at least this visible are test targets.
MIN_VISIB_FRACT = 0.1
OBJ_IDS = (1, 2, 3)
SPLITS = ("train_pbr", "train_primesense", "test_primesense")

_MARGIN_PX = 2.0  # every projected vertex stays this far inside the image
_PLANE_ID = 0  # the test scenes' table, drawn as an extra (no BOP object)


class FixtureExistsError(FileExistsError, ValueError):
    """The output folder already exists (and ``overwrite`` is off)."""


# ------------------------------------------------------------------------------------------ rotations
def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform on SO(3): a normalised Gaussian quaternion (:func:`posediff.lie.so3.quaternion_matrix`,
    the group's own sampler), drawn from the fixture's numpy generator."""
    import torch

    from ...lie.so3 import quaternion_matrix

    return quaternion_matrix(torch.from_numpy(rng.standard_normal(4))).numpy()


def _axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that map coordinate axes onto coordinate axes (resting poses on a table)."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            M = np.zeros((3, 3))
            for row, (col, sgn) in enumerate(zip(perm, signs, strict=True)):
                M[row, col] = -1.0 if sgn else 1.0
            if np.linalg.det(M) > 0:
                out.append(M)
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV world→camera ``(R_w2c, t_w2c)`` of a camera at ``eye`` looking at ``target``, image y
    pointing along ``-up`` as far as possible."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking along up: any perpendicular will do
        x = np.cross(z, np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


# --------------------------------------------------------------------------------------------- models
def make_model(obj_id: int) -> Any:
    """The ``trimesh.Trimesh`` (mm) of fixture object ``obj_id`` (module docstring), vertices split
    at sharp edges so that its vertex normals are the faces' (flat faces, smooth cylinder side) and
    rounded to float32 (as the PLY files store them). Load the PLY files with ``process=False`` to
    keep the split vertices."""
    import trimesh

    if obj_id == 1:  # cylinder, radius 22, height 60
        mesh = trimesh.creation.cylinder(radius=22.0, height=60.0, sections=48)
    elif obj_id == 2:  # box 76 x 48 x 30
        mesh = trimesh.creation.box(extents=(76.0, 48.0, 30.0))
    elif obj_id == 3:  # L bracket: base plate, upright plate at one end, off-centre peg on the base
        base = trimesh.creation.box(extents=(70.0, 36.0, 10.0))
        upright = trimesh.creation.box(extents=(12.0, 36.0, 44.0))
        upright.apply_translation((29.0, 0.0, 27.0))
        peg = trimesh.creation.cylinder(radius=6.0, height=16.0, sections=24)
        peg.apply_translation((-18.0, 9.0, 13.0))
        mesh = trimesh.util.concatenate([base, upright, peg])
        mesh.apply_translation(-mesh.bounds.mean(axis=0))
    else:
        raise ValueError(f"the fixture has objects {list(OBJ_IDS)}, not {obj_id}")
    mesh = trimesh.graph.smooth_shade(mesh, angle=math.radians(30.0))
    # PLY stores float32: round here so the rendered, measured and written models are the same
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)
    return mesh


def model_symmetries(obj_id: int) -> dict[str, Any]:
    """The ``symmetries_continuous`` / ``symmetries_discrete`` entries of ``models_info.json`` of
    object ``obj_id`` (a key is absent when the object has none of that kind)."""

    def flat(R: np.ndarray) -> list[float]:
        T = np.eye(4)
        T[:3, :3] = np.rint(R)
        return [float(v) + 0.0 for v in T.reshape(-1)]  # + 0.0: no "-0.0" in the JSON

    if obj_id == 1:
        return {
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
            "symmetries_discrete": [flat(rot_x(math.pi))],
        }
    if obj_id == 2:
        return {"symmetries_discrete": [flat(rot_x(math.pi)), flat(rot_y(math.pi)), flat(rot_z(math.pi))]}
    if obj_id == 3:
        return {}
    raise ValueError(f"the fixture has objects {list(OBJ_IDS)}, not {obj_id}")


def diameter(vertices: np.ndarray) -> float:
    """The largest distance between two of ``vertices`` (N, 3), exactly (on the convex hull)."""
    import trimesh

    V = np.asarray(vertices, dtype=np.float64)
    try:
        V = trimesh.convex.convex_hull(V).vertices
    except Exception:  # degenerate (flat) point set: use them all
        pass
    best = 0.0
    for i in range(0, len(V), 256):
        d = np.linalg.norm(V[i : i + 256, None, :] - V[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best


def model_info(obj_id: int, mesh: Any) -> dict[str, Any]:
    """The ``models_info.json`` entry of ``mesh``: diameter, bounding box, symmetries."""
    lo, size = mesh.bounds[0], mesh.extents
    info: dict[str, Any] = {"diameter": diameter(mesh.vertices)}
    for k, axis in enumerate("xyz"):
        info[f"min_{axis}"] = float(lo[k])
    for k, axis in enumerate("xyz"):
        info[f"size_{axis}"] = float(size[k])
    info.update(model_symmetries(obj_id))
    return info


def camera(width: int, height: int) -> dict[str, float]:
    """``camera_primesense.json``: T-LESS primesense intrinsics scaled to ``width`` x ``height``."""
    sx, sy = width / TLESS_PRIMESENSE["width"], height / TLESS_PRIMESENSE["height"]
    return {
        "cx": TLESS_PRIMESENSE["cx"] * sx,
        "cy": TLESS_PRIMESENSE["cy"] * sy,
        "depth_scale": DEPTH_SCALE,
        "fx": TLESS_PRIMESENSE["fx"] * sx,
        "fy": TLESS_PRIMESENSE["fy"] * sy,
        "height": int(height),
        "width": int(width),
    }


def _K(cam: dict[str, float]) -> np.ndarray:
    return np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------- summary
@dataclass
class SplitCounts:
    scenes: int = 0
    images: int = 0
    instances: int = 0


@dataclass
class BopFixtureSummary:
    """What :func:`make_bop_fixture` wrote: counts per split, test targets, the lowest test
    ``visib_fract``, the time taken."""

    path: Path
    splits: dict[str, SplitCounts] = field(default_factory=dict)
    targets: int = 0
    target_instances: int = 0
    min_test_visib_fract: float = 1.0
    seconds: float = 0.0

    @property
    def images(self) -> int:
        return sum(c.images for c in self.splits.values())

    def line(self) -> str:
        parts = ", ".join(
            f"{name} {c.scenes} scenes / {c.images} images / {c.instances} instances"
            for name, c in self.splits.items()
        )
        return (
            f"BOP fixture in {self.path}: {len(OBJ_IDS)} objects; {parts}; {self.targets} test targets "
            f"({self.target_instances} instances, lowest visib_fract {self.min_test_visib_fract:.2f}) "
            f"in {self.seconds:.1f} s"
        )


# ----------------------------------------------------------------------------------------- writing
def _dump_by_key(data: dict[str, Any]) -> str:
    """A JSON object with one top-level key per line (readable, like BOP's files)."""
    lines = [f"  {json.dumps(k)}: {json.dumps(v, sort_keys=True)}" for k, v in data.items()]
    return "{\n" + ",\n".join(lines) + "\n}\n"


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


def _imwrite(path: Path, image: np.ndarray) -> None:
    import cv2

    if image.ndim == 3:
        image = np.ascontiguousarray(image[..., ::-1])  # RGB → BGR
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix == ".jpg" else []
    if not cv2.imwrite(str(path), image, params):
        raise RuntimeError(f"could not write {path}")


def _bbox(mask: np.ndarray) -> list[int]:
    ys = np.flatnonzero(mask.any(axis=1))
    xs = np.flatnonzero(mask.any(axis=0))
    if len(ys) == 0:
        return [-1, -1, -1, -1]
    return [int(xs[0]), int(ys[0]), int(xs[-1] - xs[0] + 1), int(ys[-1] - ys[0] + 1)]


def _flat(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


class _SceneWriter:
    """Writes one scene folder image by image, then its three JSON files."""

    def __init__(self, root: Path, rgb_ext: str) -> None:
        self.root, self.rgb_ext = root, rgb_ext
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        self.gt: dict[str, Any] = {}
        self.camera: dict[str, Any] = {}
        self.info: dict[str, Any] = {}

    def add(
        self,
        im_id: int,
        out: RenderedScene,
        instances: list[tuple[int, np.ndarray, np.ndarray]],
        K: np.ndarray,
        world: tuple[np.ndarray, np.ndarray] | None,
    ) -> list[float]:
        name = f"{im_id:06d}"
        _imwrite(self.root / "rgb" / f"{name}{self.rgb_ext}", out.rgb)
        depth_png = np.clip(np.rint(out.depth / DEPTH_SCALE), 0, 65535).astype(np.uint16)
        _imwrite(self.root / "depth" / f"{name}.png", depth_png)
        gts, infos, visib = [], [], []
        for gt_idx, (obj_id, R, t) in enumerate(instances):
            mask = out.mask(gt_idx)
            mask_visib = out.mask_visib(gt_idx, VISIB_TOLERANCE_MM)
            _imwrite(self.root / "mask" / f"{name}_{gt_idx:06d}.png", mask.astype(np.uint8) * 255)
            _imwrite(self.root / "mask_visib" / f"{name}_{gt_idx:06d}.png", mask_visib.astype(np.uint8) * 255)
            n_all, n_visib = int(mask.sum()), int(mask_visib.sum())
            fract = n_visib / n_all if n_all else 0.0
            gts.append({"cam_R_m2c": _flat(R), "cam_t_m2c": _flat(t), "obj_id": int(obj_id)})
            infos.append(
                {
                    "bbox_obj": _bbox(mask),
                    "bbox_visib": _bbox(mask_visib),
                    "px_count_all": n_all,
                    "px_count_valid": int((mask & (depth_png > 0)).sum()),
                    "px_count_visib": n_visib,
                    "visib_fract": fract,
                }
            )
            visib.append(fract)
        cam: dict[str, Any] = {"cam_K": _flat(K), "depth_scale": DEPTH_SCALE}
        if world is not None:
            cam["cam_R_w2c"], cam["cam_t_w2c"] = _flat(world[0]), _flat(world[1])
        self.gt[str(im_id)] = gts
        self.camera[str(im_id)] = cam
        self.info[str(im_id)] = infos
        return visib

    def close(self) -> None:
        _write_text(self.root / "scene_gt.json", _dump_by_key(self.gt))
        _write_text(self.root / "scene_camera.json", _dump_by_key(self.camera))
        _write_text(self.root / "scene_gt_info.json", _dump_by_key(self.info))


# ------------------------------------------------------------------------------------------- scenes
def _background(rng: np.random.Generator, height: int, width: int, dim: float = 1.0) -> np.ndarray:
    """A random coloured / textured (H, W, 3) uint8 image: a gradient, a checkerboard or stripes,
    with noise."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    c0, c1 = rng.uniform(0, 255, 3).astype(np.float32), rng.uniform(0, 255, 3).astype(np.float32)
    kind = int(rng.integers(3))
    if kind == 0:
        a = rng.uniform(0, 2 * math.pi)
        s = xs * math.cos(a) + ys * math.sin(a)
        w = (s - s.min()) / max(float(s.max() - s.min()), 1.0)
    elif kind == 1:
        cell = int(rng.integers(8, 33))
        w = (((xs // cell) + (ys // cell)) % 2).astype(np.float32)
    else:
        a, period = rng.uniform(0, math.pi), rng.uniform(6, 30)
        w = 0.5 + 0.5 * np.sin((xs * math.cos(a) + ys * math.sin(a)) * (2 * math.pi / period))
    img = c0 + w[..., None] * (c1 - c0) + rng.normal(0, 8, (height, width, 3)).astype(np.float32)
    return np.clip(img * dim, 0, 255).astype(np.uint8)


def _obj_ids(rng: np.random.Generator, n: int) -> list[int]:
    """``n`` object ids: each object once (as far as ``n`` allows), the rest drawn at random (so at
    least one object has several instances when ``n`` > 3), ascending."""
    first = [int(i) for i in rng.permutation(OBJ_IDS)[: min(n, len(OBJ_IDS))]]
    rest = [int(i) for i in rng.choice(OBJ_IDS, size=max(0, n - len(OBJ_IDS)))]
    return sorted(first + rest)


class _Scenes:
    """The scene makers, sharing the models, the camera and one renderer."""

    def __init__(self, renderer: BopRenderer, models: dict[int, Any], width: int, height: int) -> None:
        self.renderer, self.width, self.height = renderer, width, height
        self.hull = {i: np.asarray(m.convex_hull.vertices) for i, m in models.items()}
        self.radius = {i: float(np.linalg.norm(v, axis=1).max()) for i, v in self.hull.items()}

    def inside(self, instances: list[tuple[int, np.ndarray, np.ndarray]], K: np.ndarray) -> bool:
        """Whether every instance lies in front of the camera and wholly inside the image."""
        for obj_id, R, t in instances:
            p = self.hull[obj_id] @ R.T + t
            if p[:, 2].min() < 2 * self.renderer.znear:
                return False
            uv = p[:, :2] / p[:, 2:] * np.diag(K)[:2] + K[:2, 2]
            if (uv.min(axis=0) < _MARGIN_PX).any():
                return False
            if uv[:, 0].max() > self.width - 1 - _MARGIN_PX or uv[:, 1].max() > self.height - 1 - _MARGIN_PX:
                return False
        return True

    @staticmethod
    def to_camera(world_objs: list, R_w2c: np.ndarray, t_w2c: np.ndarray) -> list:
        return [(i, R_w2c @ R, R_w2c @ t + t_w2c) for i, R, t in world_objs]

    def pbr_world(self, rng: np.random.Generator, n: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``n`` instances at random orientations in a ball, bounding spheres 2 mm apart."""
        placed: list[tuple[int, np.ndarray, np.ndarray]] = []
        ball = 40.0
        for obj_id in _obj_ids(rng, n):
            for attempt in range(10_000):
                d = rng.standard_normal(3)
                p = d / np.linalg.norm(d) * ball * rng.uniform() ** (1 / 3)
                if all(
                    np.linalg.norm(p - q) >= self.radius[obj_id] + self.radius[j] + 2.0 for j, _, q in placed
                ):
                    break
                if attempt % 50 == 49:
                    ball += 5.0
            placed.append((obj_id, _random_rotation(rng), p))
        if not placed:
            return []
        centre = np.mean([p for _, _, p in placed], axis=0)
        return [(i, R, p - centre) for i, R, p in placed]

    def table_world(self, rng: np.random.Generator, n: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``n`` instances resting on the plane z = 0 (a random axis-aligned resting pose and a
        random turn about z), placed one by one as close as their footprints allow (1–4 mm gaps)."""
        rests = _axis_rotations()
        placed: list[tuple[int, np.ndarray, np.ndarray, float]] = []
        for obj_id in _obj_ids(rng, n):
            R = rot_z(rng.uniform(0, 2 * math.pi)) @ rests[int(rng.integers(len(rests)))]
            v = self.hull[obj_id] @ R.T
            r = float(np.linalg.norm(v[:, :2], axis=1).max())
            z = -float(v[:, 2].min())
            a = rng.uniform(0, 2 * math.pi)
            u = np.array([math.cos(a), math.sin(a), 0.0])
            gap = rng.uniform(1.0, 4.0)
            dist = 0.0
            while any(np.linalg.norm(dist * u - q * [1, 1, 0]) < r + rq + gap for _, _, q, rq in placed):
                dist += 1.0
            placed.append((obj_id, R, dist * u + [0.0, 0.0, z], r))
        if not placed:
            return []
        centre = np.mean([p for _, _, p, _ in placed], axis=0) * [1, 1, 0]
        return [(i, R, p - centre) for i, R, p, _ in placed]

    def view(
        self, rng: np.random.Generator, world: list, K: np.ndarray, draw: Any
    ) -> tuple[np.ndarray, np.ndarray, list]:
        """A camera from ``draw(rng, extra_distance) -> (R_w2c, t_w2c)`` that sees every instance
        whole (moved back 25 mm every 20 failed draws); returns it and the camera-frame instances."""
        extra = 0.0
        for attempt in range(2000):
            R_w2c, t_w2c = draw(rng, extra)
            instances = self.to_camera(world, R_w2c, t_w2c)
            if self.inside(instances, K):
                return R_w2c, t_w2c, instances
            if attempt % 20 == 19:
                extra += 25.0
        raise RuntimeError("could not find a camera that sees every instance; use a larger image")

    @staticmethod
    def pbr_camera(rng: np.random.Generator, extra: float) -> tuple[np.ndarray, np.ndarray]:
        """From any direction, 600–700 mm (+ ``extra``) from the scene centre, rolled up to ±0.5 rad."""
        d = rng.standard_normal(3)
        eye = d / np.linalg.norm(d) * (rng.uniform(600.0, 700.0) + extra)
        R, t = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        roll = rot_z(rng.uniform(-0.5, 0.5))  # about the optical axis
        return roll @ R, roll @ t

    def table_camera(
        self, rng: np.random.Generator, extra: float, world: list, occluding: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """20–50° above the table at a random azimuth, 600–700 mm (+ ``extra``) from the cluster;
        ``occluding``: 8–14° above the table, looking at the lowest instance through the tallest."""
        tops = [float((self.hull[i] @ R.T)[:, 2].max() + t[2]) for i, R, t in world]
        tall = int(np.argmax(tops))
        others = [k for k in range(len(world)) if k != tall]
        if occluding and others:
            short = min(others, key=lambda k: tops[k])
            behind = world[short][2] * [1.0, 1.0, 0.0]
            u = world[tall][2] * [1.0, 1.0, 0.0] - behind
            az = math.atan2(u[1], u[0]) + rng.uniform(-0.1, 0.1)
            el = math.radians(rng.uniform(8.0, 14.0))
            target = behind + [0.0, 0.0, 0.5 * tops[short]]
        else:
            az = rng.uniform(0, 2 * math.pi)
            el = math.radians(rng.uniform(20.0, 50.0))
            target = np.array([0.0, 0.0, 20.0])
        dist = rng.uniform(600.0, 700.0) + extra
        eye = target + dist * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
        )
        return look_at(eye, target, np.array([0.0, 0.0, 1.0]))


def _sphere_directions(n: int, offset: float) -> np.ndarray:
    """``n`` roughly even directions on the unit sphere (a Fibonacci spiral turned by ``offset``)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    a = k * math.pi * (3.0 - math.sqrt(5.0)) + offset
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)


# -------------------------------------------------------------------------------------------- splits
def _train_pbr(
    root: Path,
    scenes: _Scenes,
    rng: np.random.Generator,
    K: np.ndarray,
    n_scenes: int,
    n_images: int,
    n_inst: int,
    say: Any,
) -> SplitCounts:
    """Clutter at random orientations over random backgrounds (rgb .jpg), with a camera of its own:
    square pixels, principal point at the image centre."""
    counts = SplitCounts()
    renderer = scenes.renderer
    K_pbr = K.copy()
    K_pbr[0, 0] = K_pbr[1, 1] = 0.5 * (K[0, 0] + K[1, 1])
    K_pbr[0, 2], K_pbr[1, 2] = scenes.width / 2, scenes.height / 2  # the image centre (render.py)
    for scene_id in range(n_scenes):
        writer = _SceneWriter(root / "train_pbr" / f"{scene_id:06d}", ".jpg")
        world = scenes.pbr_world(rng, n_inst)
        for im_id in range(n_images):
            R_w2c, t_w2c, inst = scenes.view(rng, world, K_pbr, scenes.pbr_camera)
            background = _background(rng, scenes.height, scenes.width)
            writer.add(
                im_id, renderer.render(inst, K_pbr, background=background), inst, K_pbr, (R_w2c, t_w2c)
            )
            counts.images += 1
            counts.instances += len(inst)
        writer.close()
        counts.scenes += 1
        say("train_pbr", scene_id, n_images, n_images * len(world))
    return counts


def _train_primesense(
    root: Path, scenes: _Scenes, rng: np.random.Generator, K: np.ndarray, n_views: int, say: Any
) -> SplitCounts:
    """Each object alone on black (scene id = obj id), 650 mm away, from a sphere of directions."""
    counts = SplitCounts()
    if n_views == 0:
        return counts
    for obj_id in OBJ_IDS:
        writer = _SceneWriter(root / "train_primesense" / f"{obj_id:06d}", ".png")
        for im_id, d in enumerate(_sphere_directions(n_views, rng.uniform(0, 2 * math.pi))):
            R_w2c, t_w2c = look_at(d * 650.0, np.zeros(3), np.array([0.0, 0.0, 1.0]))
            inst = [(obj_id, R_w2c, t_w2c)]
            writer.add(im_id, scenes.renderer.render(inst, K), inst, K, (R_w2c, t_w2c))
            counts.images += 1
            counts.instances += 1
        writer.close()
        counts.scenes += 1
        say("train_primesense", obj_id, n_views, n_views)
    return counts


def _test_primesense(
    root: Path,
    scenes: _Scenes,
    rng: np.random.Generator,
    K: np.ndarray,
    n_scenes: int,
    n_images: int,
    n_inst: int,
    say: Any,
) -> tuple[SplitCounts, list[dict[str, int]], float]:
    """Objects close together on a table plane (scene ids from 1); image 0 of each scene looks at
    the lowest instance through the tallest, from low above the table. Returns the counts, the
    BOP19 targets and the lowest visib_fract."""
    import trimesh

    counts = SplitCounts()
    renderer = scenes.renderer
    plane = trimesh.creation.box(extents=(3000.0, 3000.0, 1.0))
    plane.apply_translation((0.0, 0.0, -0.5))
    targets: list[dict[str, int]] = []
    min_visib = 1.0
    for scene_id in range(1, n_scenes + 1):
        renderer.add_model(_PLANE_ID, plane, color=tuple(rng.uniform(0.25, 0.5, 3)))
        writer = _SceneWriter(root / "test_primesense" / f"{scene_id:06d}", ".png")
        world = scenes.table_world(rng, n_inst)
        for im_id in range(n_images):

            def draw(r: np.random.Generator, extra: float, occluding: bool = im_id == 0) -> Any:
                return scenes.table_camera(r, extra, world, occluding)  # noqa: B023 — called at once

            R_w2c, t_w2c, inst = scenes.view(rng, world, K, draw)
            background = _background(rng, scenes.height, scenes.width, dim=0.5)
            out = renderer.render(inst, K, background=background, extras=[(_PLANE_ID, R_w2c, t_w2c)])
            visib = writer.add(im_id, out, inst, K, (R_w2c, t_w2c))
            counts.images += 1
            counts.instances += len(inst)
            min_visib = min(min_visib, *visib)
            per_obj: dict[int, int] = {}
            for (obj_id, _, _), v in zip(inst, visib, strict=True):
                if v >= MIN_VISIB_FRACT:
                    per_obj[obj_id] = per_obj.get(obj_id, 0) + 1
            for obj_id in sorted(per_obj):
                targets.append(
                    {"im_id": im_id, "inst_count": per_obj[obj_id], "obj_id": obj_id, "scene_id": scene_id}
                )
        writer.close()
        counts.scenes += 1
        say("test_primesense", scene_id, n_images, n_images * len(world))
    return counts, targets, min_visib


# -------------------------------------------------------------------------------------------- main
def make_bop_fixture(
    out: str | os.PathLike[str],
    *,
    seed: int = 0,
    width: int = 320,
    height: int = 240,
    pbr_scenes: int = 2,
    pbr_images: int = 6,
    pbr_instances: int = 5,
    train_views: int = 6,
    test_scenes: int = 2,
    test_images: int = 3,
    test_instances: int = 6,
    overwrite: bool = False,
    progress: bool = False,
) -> BopFixtureSummary:
    """Write the fixture (module docstring) to ``out``, built in ``<out>.partial`` and renamed.

    ``pbr_scenes`` x ``pbr_images`` images of ``pbr_instances`` objects each (train_pbr);
    ``train_views`` views of each object alone (train_primesense); ``test_scenes`` x
    ``test_images`` images of ``test_instances`` objects on a table (test_primesense). The same
    ``seed`` gives the same files. An existing ``out`` is refused (:class:`FixtureExistsError`)
    unless ``overwrite``, and even then only when make-bop made it (its ``.posediff-output`` marker;
    ``posediff._io.check_output_dir``). ``progress`` prints one line per scene.
    """
    start = time.perf_counter()
    out = Path(out)
    sizes = {
        "width": width,
        "height": height,
        "pbr_scenes": pbr_scenes,
        "pbr_images": pbr_images,
        "pbr_instances": pbr_instances,
        "train_views": train_views,
        "test_scenes": test_scenes,
        "test_images": test_images,
        "test_instances": test_instances,
    }
    least = {"width": 16, "height": 16, "pbr_instances": 1, "test_instances": 1}
    for key, value in sizes.items():
        if int(value) != value or value < least.get(key, 0):
            raise ValueError(f"{key} must be a whole number >= {least.get(key, 0)}, got {value}")
    if out.exists() and not overwrite:
        raise FixtureExistsError(f"{out} already exists; choose another out= or pass overwrite=true")
    command = "posediff data make-bop"
    check_output_dir(out, command, replace=overwrite)  # overwrite: only a folder make-bop made itself
    partial = out.with_name(out.name + ".partial")
    remove_own_dir(partial, command)
    make_output_dir(partial, command)
    for split in SPLITS:  # present even when a split is sized to nothing
        (partial / split).mkdir()

    renderer: BopRenderer | None = None
    try:
        summary = BopFixtureSummary(path=out)
        cam = camera(width, height)
        K = _K(cam)
        _write_text(partial / "camera_primesense.json", json.dumps(cam, indent=2, sort_keys=True) + "\n")
        models = {obj_id: make_model(obj_id) for obj_id in OBJ_IDS}
        info = {str(obj_id): model_info(obj_id, mesh) for obj_id, mesh in models.items()}
        for folder in ("models", "models_eval"):
            (partial / folder).mkdir()
            _write_text(partial / folder / "models_info.json", _dump_by_key(info))
            for obj_id, mesh in models.items():
                data = mesh.export(file_type="ply", encoding="binary", vertex_normal=True)
                (partial / folder / f"obj_{obj_id:06d}.ply").write_bytes(data)

        renderer = BopRenderer(width, height)
        greys = {1: 0.72, 2: 0.62, 3: 0.68}  # T-LESS-like greys, a little apart
        for obj_id, mesh in models.items():
            renderer.add_model(obj_id, mesh, color=(greys[obj_id],) * 3)
        scenes = _Scenes(renderer, models, width, height)

        def say(split: str, scene_id: int, images: int, instances: int) -> None:
            if progress:
                print(f"  {split}/{scene_id:06d}: {images} images, {instances} instances", flush=True)

        summary.splits["train_pbr"] = _train_pbr(
            partial, scenes, np.random.default_rng([seed, 0]), K, pbr_scenes, pbr_images, pbr_instances, say
        )
        summary.splits["train_primesense"] = _train_primesense(
            partial, scenes, np.random.default_rng([seed, 1]), K, train_views, say
        )
        summary.splits["test_primesense"], targets, min_visib = _test_primesense(
            partial,
            scenes,
            np.random.default_rng([seed, 2]),
            K,
            test_scenes,
            test_images,
            test_instances,
            say,
        )
        lines = [json.dumps(t, sort_keys=True) for t in targets]
        text = "[\n  " + ",\n  ".join(lines) + "\n]\n" if lines else "[]\n"
        _write_text(partial / "test_targets_bop19.json", text)
        summary.targets = len(targets)
        summary.target_instances = sum(t["inst_count"] for t in targets)
        summary.min_test_visib_fract = min_visib
    except BaseException:
        remove_own_dir(partial, command)
        raise
    finally:
        if renderer is not None:
            renderer.close()
    replace_dir(partial, out, command)
    summary.seconds = time.perf_counter() - start
    return summary


__all__ = [
    "DEPTH_SCALE",
    "MIN_VISIB_FRACT",
    "OBJ_IDS",
    "SPLITS",
    "TLESS_PRIMESENSE",
    "BopFixtureSummary",
    "FixtureExistsError",
    "SplitCounts",
    "camera",
    "diameter",
    "look_at",
    "make_bop_fixture",
    "make_model",
    "model_info",
    "model_symmetries",
]
