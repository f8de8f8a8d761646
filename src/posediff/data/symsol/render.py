"""Headless rendering of the SYMSOL shapes with pyrender over EGL (Mesa's software EGL on a CPU
machine, NVIDIA's EGL on a GPU machine).

Camera as the authors' SYMSOL-T (``../shared/docs/reference-implementation.md`` §7.3): square
image, 60° field of view, principal point at the image centre, the scene centre
:data:`SCENE_DISTANCE` = 5.25 / tan 30° ≈ 9.093 units in front of the camera; black background,
grey shading (a key light at the camera and a weaker fill light, both fixed to the camera, so faces
at different angles differ in brightness and symmetric poses render alike).

Poses are camera-frame ``[R | t]`` in the OpenCV convention (x right, y down, z forward): a point
``p`` of the object lands at ``K (R p + t)``.

The traps of offscreen GL in a PyTorch process are handled by :mod:`posediff.data.offscreen`
(``triton`` imported first, ``LP_NUM_THREADS=0``); the GL context is created lazily, on the first
:meth:`SymsolRenderer.render` call in the process that renders, and a renderer pickles without its
context, so each ``DataLoader`` worker makes its own. ``PYOPENGL_PLATFORM`` defaults to ``egl``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...symmetry import SHAPES
from ..offscreen import CV_TO_GL, import_pyrender, offscreen_renderer, prepare_gl, release
from .shapes import SHAPE_IDS, make_mesh, shape_name

#: Half-width (units) of the view frustum at the scene centre, and the field of view: the authors'.
FRUSTUM_HALF_WIDTH = 5.25
FOV_DEG = 60.0
#: Distance of the scene centre (translation 0 of SYMSOL-T) from the camera: 5.25 / tan 30°.
SCENE_DISTANCE = FRUSTUM_HALF_WIDTH / math.tan(math.radians(FOV_DEG / 2.0))
#: The smallest image side the renderer makes (pixels).
MIN_IMAGE_SIZE = 8


def intrinsics(image_size: int, fov_deg: float = FOV_DEG) -> np.ndarray:
    """``(3, 3)`` float64 pinhole K of a square ``image_size`` image with horizontal field of view
    ``fov_deg``: f = (W/2) / tan(fov/2), principal point (W/2, W/2) (224 px: f = 193.99, c = 112)."""
    f = (image_size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    c = image_size / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


@dataclass
class Rendered:
    """One rendered view. ``rgb`` (H, W, 3) uint8; ``mask`` (H, W) bool, the visible object pixels;
    ``depth`` (H, W) float32, z in camera units (0 = background); ``K`` (3, 3); ``R`` (3, 3) and
    ``t`` (3,) the camera-frame pose; ``shape_id`` the index in ``SHAPES``."""

    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    shape_id: int


class SymsolRenderer:
    """Renders the five shapes at camera-frame poses; one lazily-created offscreen GL context.

    ``SymsolRenderer(image_size=224)(shape, R, t)`` → :class:`Rendered`. ``key_light`` and
    ``fill_light`` are directional-light intensities, ``ambient`` the ambient grey level, ``grey``
    the base colour of the (matte, flat-shaded) material.
    """

    def __init__(
        self,
        image_size: int = 224,
        *,
        fov_deg: float = FOV_DEG,
        key_light: float = 1.6,
        fill_light: float = 1.6,
        ambient: float = 0.1,
        grey: float = 0.75,
    ) -> None:
        if (
            isinstance(image_size, bool)
            or not isinstance(image_size, (int, np.integer))
            or image_size < MIN_IMAGE_SIZE
        ):
            raise ValueError(
                f"image_size must be an integer of at least {MIN_IMAGE_SIZE} (pixels), got {image_size!r}"
            )
        self.image_size = int(image_size)
        self.fov_deg = float(fov_deg)
        self.K = intrinsics(self.image_size, self.fov_deg)
        self.key_light, self.fill_light, self.ambient, self.grey = key_light, fill_light, ambient, grey
        self._gl: Any = None  # (OffscreenRenderer, {shape: (scene, mesh node)})

    def settings(self) -> dict[str, float | int | str]:
        """What defines the images besides the poses: the camera and the shading (recorded in every
        shard and in ``meta.json`` so a resumed render or a reader can tell renders apart)."""
        return {
            "image_size": self.image_size,
            "fov_deg": self.fov_deg,
            "key_light": float(self.key_light),
            "fill_light": float(self.fill_light),
            "ambient": float(self.ambient),
            "grey": float(self.grey),
            "material": "matte flat-shaded",
            "scene_distance": SCENE_DISTANCE,
        }

    # A live GL context cannot cross a process boundary: pickle without it, rebuild on first use.
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_gl"] = None
        return state

    def _setup(self) -> Any:
        pyrender = import_pyrender()

        W = self.image_size
        f, c = self.K[0, 0], self.K[0, 2]
        material = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=[self.grey, self.grey, self.grey, 1.0], metallicFactor=0.0, roughnessFactor=1.0
        )
        fill_pose = np.eye(4)
        a, b = math.radians(50.0), math.radians(-55.0)  # fill light from the upper left of the view
        rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        fill_pose[:3, :3] = ry @ rx
        scenes = {}
        for shape in SHAPES:
            scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[self.ambient] * 3)
            node = scene.add(pyrender.Mesh.from_trimesh(make_mesh(shape), material=material, smooth=False))
            scene.add(pyrender.IntrinsicsCamera(f, f, c, c, znear=0.05, zfar=100.0), pose=np.eye(4))
            scene.add(pyrender.DirectionalLight(intensity=self.key_light), pose=np.eye(4))
            scene.add(pyrender.DirectionalLight(intensity=self.fill_light), pose=fill_pose)
            scenes[shape] = (scene, node)
        renderer = offscreen_renderer(W, W)
        return renderer, scenes

    def __call__(self, shape: str | int, R: np.ndarray, t: np.ndarray) -> Rendered:
        return self.render(shape, R, t)

    def render(self, shape: str | int, R: Any, t: Any) -> Rendered:
        """Render ``shape`` at the camera-frame pose ``R`` (3, 3), ``t`` (3,) (arrays or tensors)."""
        name = shape_name(shape)
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        if self._gl is None:
            self._gl = self._setup()
        renderer, scenes = self._gl
        scene, node = scenes[name]
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R, t
        scene.set_pose(node, CV_TO_GL @ pose)
        rgb, depth = renderer.render(scene)
        depth = np.asarray(depth, dtype=np.float32)
        return Rendered(
            rgb=np.ascontiguousarray(rgb[..., :3], dtype=np.uint8),
            mask=depth > 0,
            depth=depth,
            K=self.K.copy(),
            R=R,
            t=t,
            shape_id=SHAPE_IDS[name],
        )

    def close(self) -> None:
        """Release the GL context (a later render makes a new one); other renderers stay usable
        (:func:`posediff.data.offscreen.release`)."""
        if self._gl is None:
            return
        renderer, self._gl = self._gl[0], None
        release(renderer)

    def __del__(self) -> None:  # pragma: no cover — best effort at interpreter exit
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        return f"SymsolRenderer(image_size={self.image_size}, fov_deg={self.fov_deg})"


__all__ = [
    "FOV_DEG",
    "FRUSTUM_HALF_WIDTH",
    "MIN_IMAGE_SIZE",
    "SCENE_DISTANCE",
    "Rendered",
    "SymsolRenderer",
    "intrinsics",
    "prepare_gl",
]
