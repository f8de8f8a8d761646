"""Offscreen rendering of BOP object meshes (millimetres) with pyrender over EGL.

:class:`BopRenderer` draws any number of instances of registered models at OpenCV model→camera
poses (x right, y down, z forward; a model point ``p`` lands at ``K (R p + t)``) with any pinhole
``K``, and returns the colour image, the scene depth and the depth of each instance rendered alone
(BOP's ``mask`` is ``instance depth > 0``; its ``mask_visib`` is where the instance's depth equals
the scene depth). :meth:`BopRenderer.render_depth` renders one object alone, depth only — what the
VSD error needs for an estimated pose.

Pixel convention: the BOP toolkit's renderers' (``renderer_vispy``, ``renderer_cpp``): ``K`` is handed
to GL as given, so a point that ``K`` projects to image coordinates ``(u, v)`` lands at GL window
coordinates ``(u, v)`` (rows counted from the top), where pixel ``(col, row)`` spans
``[col, col + 1) × [row, row + 1)`` and is sampled at its centre ``(col + ½, row + ½)``. By default every
pixel is sampled once, at that centre (pyrender's multisampling is switched off, see
``antialias``), so pixel ``(col, row)`` belongs to an object's mask exactly when the ray through
image coordinates ``(col + ½, row + ½)`` hits the object. The real BOP datasets' depth images,
masks and ``visib_fract`` were rendered this way, so posediff's VSD renders match them. (OpenCV's
convention, pixel centres at integer coordinates, is half a pixel away; posediff's crops,
:mod:`posediff.data.bop.roi`, use OpenCV's, as the images are resampled with it.)

Shading: a grey matte material (T-LESS objects are texture-less grey; a colour per model is
optional), flat-shaded, with a key light along the viewing direction and a weaker fill light from the
upper left, both fixed to the camera, so faces at different angles differ in shade.

The GL traps of a PyTorch process are handled by :mod:`posediff.data.offscreen`: ``triton`` imported
before the first context, the context created lazily (a renderer pickles without it) and
:meth:`close` destroying only this renderer's context, never the process-wide EGL display.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..offscreen import CV_TO_GL, import_pyrender, offscreen_renderer, release

#: Default tolerance (mm) between an instance's own depth and the scene depth for a pixel of the
#: instance to count as visible (rendered depths of the same surface agree to ~1e-3 mm).
VISIB_TOLERANCE_MM = 1.0


@dataclass
class RenderedScene:
    """One rendered image. ``rgb`` (H, W, 3) uint8; ``depth`` (H, W) float32, z in mm of the whole
    scene (0 = nothing); ``depth_per_instance`` one (H, W) float32 per instance, in the order given,
    each rendered alone (empty when ``per_instance=False``)."""

    rgb: np.ndarray
    depth: np.ndarray
    depth_per_instance: list[np.ndarray]

    def mask(self, i: int) -> np.ndarray:
        """(H, W) bool: the full silhouette of instance ``i`` (BOP's ``mask``)."""
        return self.depth_per_instance[i] > 0

    def mask_visib(self, i: int, tolerance_mm: float = VISIB_TOLERANCE_MM) -> np.ndarray:
        """(H, W) bool: the visible part of instance ``i`` (BOP's ``mask_visib``): its own depth is
        set and within ``tolerance_mm`` of the scene depth."""
        own = self.depth_per_instance[i]
        return (own > 0) & (self.depth > 0) & (np.abs(own - self.depth) <= tolerance_mm)


def _pose_matrix(R: Any, t: Any) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    pose[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return pose


def _rgba(color: Sequence[float] | None, grey: float) -> tuple[float, float, float, float]:
    if color is None:
        return (grey, grey, grey, 1.0)
    c = [float(v) for v in color]
    if len(c) not in (3, 4) or not all(0.0 <= v <= 1.0 for v in c):
        raise ValueError(f"color must be 3 or 4 floats in [0, 1], got {color!r}")
    return (c[0], c[1], c[2], c[3] if len(c) == 4 else 1.0)


class _Gl:
    """The live GL state: offscreen renderer, one scene, a camera, two lights and, per model, a pool
    of mesh nodes (each its own ``pyrender.Mesh`` so that visibility is per node)."""

    def __init__(self, owner: BopRenderer) -> None:
        pyrender = import_pyrender()

        self.pyrender = pyrender
        self.owner = owner
        self.scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[owner.ambient] * 3)
        self.camera = pyrender.IntrinsicsCamera(
            1.0, 1.0, owner.width / 2, owner.height / 2, znear=owner.znear, zfar=owner.zfar
        )
        self.scene.add(self.camera, pose=np.eye(4))
        self.key = pyrender.DirectionalLight(intensity=owner.light)
        self.scene.add(self.key, pose=np.eye(4))
        a, b = math.radians(50.0), math.radians(-55.0)  # fill light from the upper left of the view
        rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        fill_pose = np.eye(4)
        fill_pose[:3, :3] = ry @ rx
        self.fill = pyrender.DirectionalLight(intensity=owner.fill_light)
        self.scene.add(self.fill, pose=fill_pose)
        self.slots: dict[int, list[Any]] = {}
        self.renderer = offscreen_renderer(owner.width, owner.height)
        if not owner.antialias:
            self._single_sample()

    def _single_sample(self) -> None:
        """Make pyrender's 4x multisample framebuffer single-sample, so that colour, depth and masks
        are all sampled at pixel centres (pyrender resolves depth by taking one of the four samples,
        ~0.4 px off the centre, which one depending on the driver)."""
        from OpenGL.GL import (
            GL_DEPTH_COMPONENT24,
            GL_RENDERBUFFER,
            GL_RGBA,
            glBindRenderbuffer,
            glRenderbufferStorageMultisample,
        )

        self.renderer.render(self.scene, flags=self.pyrender.RenderFlags.DEPTH_ONLY)  # makes the buffers
        inner = self.renderer._renderer
        w, h = self.owner.width, self.owner.height
        self.renderer._platform.make_current()
        for buffer, fmt in ((inner._main_cb_ms, GL_RGBA), (inner._main_db_ms, GL_DEPTH_COMPONENT24)):
            glBindRenderbuffer(GL_RENDERBUFFER, buffer)
            glRenderbufferStorageMultisample(GL_RENDERBUFFER, 0, fmt, w, h)
        glBindRenderbuffer(GL_RENDERBUFFER, 0)

    def drop(self, obj_id: int) -> None:
        for node in self.slots.pop(obj_id, []):
            self.scene.remove_node(node)

    def nodes(self, obj_id: int, count: int) -> list[Any]:
        """The first ``count`` nodes of ``obj_id``'s pool (made on demand)."""
        pool = self.slots.setdefault(obj_id, [])
        if len(pool) < count:
            pyrender = self.pyrender
            mesh, rgba = self.owner._models[obj_id]
            material = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=list(rgba), metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True
            )
            while len(pool) < count:
                pm = pyrender.Mesh.from_trimesh(mesh, material=material, smooth=False)
                pm.is_visible = False
                pool.append(self.scene.add(pm, pose=np.eye(4)))
        return pool[:count]

    def hide_all(self) -> None:
        for pool in self.slots.values():
            for node in pool:
                node.mesh.is_visible = False

    def set_camera(self, K: Any) -> None:
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
        self.camera.fx, self.camera.fy = float(K[0, 0]), float(K[1, 1])
        # as the BOP toolkit: the principal point as given (module docstring, "Pixel convention")
        self.camera.cx, self.camera.cy = float(K[0, 2]), float(K[1, 2])

    def place(self, instances: Sequence[tuple[int, Any, Any]]) -> list[Any]:
        """Pose one pool node per instance (hidden); returns the nodes in instance order."""
        counts: dict[int, int] = {}
        for obj_id, _, _ in instances:
            if int(obj_id) not in self.owner._models:
                raise KeyError(f"unknown obj_id {obj_id}; add_model() it first")
            counts[int(obj_id)] = counts.get(int(obj_id), 0) + 1
        pools = {obj_id: iter(self.nodes(obj_id, n)) for obj_id, n in counts.items()}
        self.hide_all()
        placed = []
        for obj_id, R, t in instances:
            node = next(pools[int(obj_id)])
            self.scene.set_pose(node, CV_TO_GL @ _pose_matrix(R, t))
            placed.append(node)
        return placed

    def depth(self) -> np.ndarray:
        flags = self.pyrender.RenderFlags.DEPTH_ONLY
        return np.array(self.renderer.render(self.scene, flags=flags), dtype=np.float32)


class BopRenderer:
    """Renders BOP models (mm) at OpenCV model→camera poses; one lazily created offscreen GL context.

    ``width``, ``height`` the image size in pixels; ``znear``, ``zfar`` the clipping range (mm).
    ``light`` (key light along the viewing direction), ``fill_light`` and ``ambient`` are the
    default light levels (each can be overridden per :meth:`render`); ``grey`` the base colour of a
    model added without its own colour. ``antialias=False`` (default) samples every pixel once, at
    its centre, so that ``rgb``, depth and masks agree exactly with ``K``; ``antialias=True`` keeps
    pyrender's 4x multisampling: smoother ``rgb`` edges, but depth (hence masks) taken from one of
    the four samples, up to ~0.4 px off the pixel centre.
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        znear: float = 10.0,
        zfar: float = 10000.0,
        light: float = 2.0,
        fill_light: float = 1.0,
        ambient: float = 0.2,
        grey: float = 0.7,
        antialias: bool = False,
    ) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not 0 < znear < zfar:
            raise ValueError(f"need 0 < znear < zfar, got znear={znear}, zfar={zfar}")
        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self.light, self.fill_light, self.ambient, self.grey = light, fill_light, ambient, grey
        self.antialias = bool(antialias)
        self._models: dict[int, tuple[Any, tuple[float, float, float, float]]] = {}
        self._gl: _Gl | None = None

    # A live GL context cannot cross a process boundary: pickle without it, rebuild on first use.
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_gl"] = None
        return state

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self._models)

    def add_model(self, obj_id: int, mesh: Any, *, color: Sequence[float] | None = None) -> None:
        """Register (or replace) model ``obj_id``: a ``trimesh.Trimesh`` in mm, in the model frame.
        ``color``: RGB(A) floats in [0, 1] (default: the renderer's grey)."""
        if len(getattr(mesh, "faces", ())) == 0:
            raise ValueError(f"model {obj_id}: the mesh has no faces")
        self._models[int(obj_id)] = (mesh, _rgba(color, self.grey))
        if self._gl is not None:
            self._gl.drop(int(obj_id))

    def _ready(self) -> _Gl:
        if self._gl is None:
            self._gl = _Gl(self)
        return self._gl

    def render(
        self,
        instances: Sequence[tuple[int, Any, Any]],
        K: Any,
        *,
        background: np.ndarray | None = None,
        extras: Sequence[tuple[int, Any, Any]] = (),
        per_instance: bool = True,
        light: float | None = None,
        fill_light: float | None = None,
        ambient: float | None = None,
    ) -> RenderedScene:
        """Render ``instances`` — ``(obj_id, R (3, 3), t (3,) mm)`` each — seen through ``K``.

        ``background``: an (H, W, 3) uint8 image behind the objects (default black), blended with
        the anti-aliased object edges; its pixels have depth 0. ``extras``: more ``(obj_id, R, t)``
        drawn into ``rgb`` and ``depth`` but given no per-instance depth (a table plane, distractors).
        ``per_instance=False`` skips the per-instance depth renders. ``light``, ``fill_light``,
        ``ambient`` override the renderer's light levels for this image.
        """
        gl = self._ready()
        gl.set_camera(K)
        gl.key.intensity = self.light if light is None else float(light)
        gl.fill.intensity = self.fill_light if fill_light is None else float(fill_light)
        amb = self.ambient if ambient is None else float(ambient)
        gl.scene.ambient_light = np.array([amb, amb, amb])
        nodes = gl.place([*instances, *extras])
        for node in nodes:
            node.mesh.is_visible = True
        rgba, depth = gl.renderer.render(gl.scene, flags=gl.pyrender.RenderFlags.RGBA)
        depth = np.array(depth, dtype=np.float32)
        color = rgba[..., :3].astype(np.float32)  # premultiplied by coverage (background alpha 0)
        if background is not None:
            bg = np.asarray(background)
            if bg.shape != (self.height, self.width, 3):
                raise ValueError(f"background must be ({self.height}, {self.width}, 3), got {bg.shape}")
            alpha = rgba[..., 3:].astype(np.float32) / 255.0
            color = color + (1.0 - alpha) * bg.astype(np.float32)
        rgb = np.clip(np.rint(color), 0, 255).astype(np.uint8)
        per: list[np.ndarray] = []
        n = len(instances)
        if per_instance and n == 1 and not extras:
            per = [depth.copy()]
        elif per_instance:
            for node in nodes:
                node.mesh.is_visible = False
            for node in nodes[:n]:
                node.mesh.is_visible = True
                per.append(gl.depth())
                node.mesh.is_visible = False
        gl.hide_all()
        return RenderedScene(rgb=rgb, depth=depth, depth_per_instance=per)

    def render_depth(self, obj_id: int, R: Any, t: Any, K: Any) -> np.ndarray:
        """(H, W) float32 depth (mm, 0 = nothing) of model ``obj_id`` alone at pose ``R``, ``t``."""
        gl = self._ready()
        gl.set_camera(K)
        (node,) = gl.place([(obj_id, R, t)])
        node.mesh.is_visible = True
        try:
            return gl.depth()
        finally:
            node.mesh.is_visible = False

    def close(self) -> None:
        """Release the GL context (a later render makes a new one); other renderers stay usable
        (:func:`posediff.data.offscreen.release`)."""
        if self._gl is None:
            return
        renderer, self._gl = self._gl.renderer, None
        release(renderer)

    def __del__(self) -> None:  # pragma: no cover — best effort at interpreter exit
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        return f"BopRenderer({self.width}x{self.height}, models={self.obj_ids})"


__all__ = ["VISIB_TOLERANCE_MM", "BopRenderer", "RenderedScene"]
