"""SYMSOL / SYMSOL-T images as the paper authors' generator makes them: exact ray casting of the
convex solids and Open3D's Phong shading, in NumPy (no GL context, no antialiasing unless asked).

**The scene** (:data:`SCENE_VERSION` 2, the paper's; ``../shared/docs/reference-implementation.md``
§7): the authors' solids (:mod:`posediff.data.symsol.shapes`), their camera (square image, 60° field
of view, principal point at the image centre, the scene centre :data:`SCENE_DISTANCE` = 5.25 / tan 30°
≈ 9.093 units in front of the camera) and their look. Their renderer is Open3D's legacy visualiser:
a grey mesh (0.7), flat-shaded, over black, lit by Open3D's default Phong lights, rasterised with
one sample per pixel (their edges jump from black to the face's grey: no antialiasing). Fitting
that model to their images (faces of 36 tetrahedra, cubes and icosahedra, interior pixels) leaves
an rms error of 0.001 (a quarter of a grey level) with a point light on the optical axis 3.8–6.1
units *behind* the camera (it sits two bounding-box extents in front of the box of everything their
window has shown, so it drifts a little from image to image) and a diffuse gain of 0.924 = 0.7 × 2 ×
0.66. For a face normal ``n``, the unit direction ``l`` to the light, ``e`` to the eye and
``r = 2(n·l)n − l`` (camera frame) a pixel's grey level is

    I = clip(albedo·(ambient + diffuse·max(0, n·l) + fill·max(0, n·l_fill)) + specular·max(0, e·r)^shininess, 0, 1)

(:class:`Look`; the paper's look is :meth:`Look.paper`; ``fill`` is a second, directional light),
then optionally gamma-encoded, blurred and noised, over a background grey level.

**Robust to the renderer**: :meth:`Look.sample` draws a look per image (light position and
strength, ambient, albedo, specular strength and sharpness, a fill light, background level,
supersampled antialiasing, gamma, blur, noise) from a seeded generator, so a varied training split
is as reproducible as a fixed one (``posediff data render look=varied``).

**Rasterisation**: a pixel (col, row) is the ray through its centre (col + ½, row + ½) — the BOP
toolkit's and OpenGL's convention; for a convex solid given by its face planes ``nₖ·x = hₖ`` the ray
``x = τ·d`` enters at ``τ = max_{nₖ·d < 0} hₖ / nₖ·d`` through that face and leaves at the smallest
``hₖ / nₖ·d`` with ``nₖ·d > 0``; it hits when it enters before it leaves. Depth is ``z = τ`` (``d_z = 1``).
``antialias = k`` shades k × k rays per pixel and averages them (the mask and depth stay one ray).

Poses are camera-frame ``[R | t]`` in the OpenCV convention (x right, y down, z forward): a point
``p`` of the object lands at ``K (R p + t)``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..offscreen import prepare_gl
from .shapes import SHAPE_IDS, make_mesh, shape_name

#: Half-width (units) of the view frustum at the scene centre, and the field of view: the authors'.
FRUSTUM_HALF_WIDTH = 5.25
FOV_DEG = 60.0
#: Distance of the scene centre (translation 0 of SYMSOL-T) from the camera: 5.25 / tan 30°.
SCENE_DISTANCE = FRUSTUM_HALF_WIDTH / math.tan(math.radians(FOV_DEG / 2.0))
#: The smallest image side the renderer makes (pixels).
MIN_IMAGE_SIZE = 8
#: The scene's version, recorded by every rendered folder: 1 — posediff's first scene (a 1.9× smaller
#: icosahedron, two-light matte shading with antialiasing, the cone's translations drawn for its centre
#: of mass); 2 — the paper's scene (module docstring).
SCENE_VERSION = 2
#: The looks a render can have: the paper's for every image, or one drawn per image.
LOOKS = ("paper", "varied")


def intrinsics(image_size: int, fov_deg: float = FOV_DEG) -> np.ndarray:
    """``(3, 3)`` float64 pinhole K of a square ``image_size`` image with horizontal field of view
    ``fov_deg``: f = (W/2) / tan(fov/2), principal point (W/2, W/2) (224 px: f = 193.99, c = 112)."""
    f = (image_size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    c = image_size / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Look:
    """How an image is lit and finished (module docstring for the shading equation).

    ``light``: the point light's camera-frame position (units); ``diffuse`` its strength, ``albedo``
    the surface grey, ``ambient`` the ambient level; ``fill`` / ``fill_direction``: a second,
    directional light (towards the scene; 0: none); ``specular`` / ``shininess``: the Phong
    highlight; ``background``: the background grey level; ``antialias``: rays per pixel side;
    ``gamma``: the output is ``I^(1/gamma)`` (1: linear, as Open3D; 2.2: sRGB-like, as pyrender);
    ``blur``: Gaussian blur std (pixels at 224 px, scaled with the image); ``noise``: Gaussian noise
    std (grey levels / 255), drawn from ``noise_seed``.
    """

    light: tuple[float, float, float] = (0.0, 0.0, -6.0)
    diffuse: float = 1.32
    albedo: float = 0.7
    ambient: float = 0.0
    fill: float = 0.0
    fill_direction: tuple[float, float, float] = (0.5, 0.5, 1.0)
    specular: float = 0.4
    shininess: float = 100.0
    background: float = 0.0
    antialias: int = 1
    gamma: float = 1.0
    blur: float = 0.0
    noise: float = 0.0
    noise_seed: int = 0

    @classmethod
    def paper(cls) -> Look:
        """The authors' look: Open3D's default Phong light on a 0.7 grey mesh over black, one ray a
        pixel (module docstring; the light 6 units behind the camera, where the fits of the cube and icosahedron put it)."""
        return cls()

    @classmethod
    def sample(cls, rng: np.random.Generator) -> Look:
        """A look drawn from ``rng`` around the paper's: what a renderer may vary (module docstring).
        The same generator state gives the same look."""
        u = rng.uniform
        coin = lambda p: bool(rng.random() < p)  # noqa: E731
        light = (u(-4.0, 4.0), u(-4.0, 4.0), u(-10.0, 2.0))
        fill_dir = rng.standard_normal(3)
        fill_dir[2] = abs(fill_dir[2]) + 0.3  # into the scene, from the camera's side
        return cls(
            light=tuple(float(x) for x in light),  # type: ignore[arg-type]
            diffuse=float(u(0.9, 1.9)),
            albedo=float(u(0.5, 0.9)),
            ambient=float(u(0.0, 0.25)) if coin(0.5) else 0.0,
            fill=float(u(0.1, 0.6)) if coin(0.4) else 0.0,
            fill_direction=tuple(float(x) for x in fill_dir),  # type: ignore[arg-type]
            specular=float(u(0.0, 0.8)),
            shininess=float(math.exp(u(math.log(5.0), math.log(300.0)))),
            background=float(u(0.0, 0.08)) if coin(0.3) else 0.0,
            antialias=int(rng.choice([1, 2, 3])) if coin(0.4) else 1,
            gamma=float(u(1.0, 2.2)) if coin(0.3) else 1.0,
            blur=float(u(0.2, 1.2)) if coin(0.3) else 0.0,
            noise=float(u(0.5, 4.0)) if coin(0.3) else 0.0,
            noise_seed=int(rng.integers(2**31)),
        )

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


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


@functools.cache
def _planes(shape: str) -> tuple[np.ndarray, np.ndarray, float]:
    """The face planes of a solid, ``N (F, 3)`` unit outward normals and offsets ``h (F,)`` with
    ``N·x ≤ h`` inside (coplanar triangles merged), and its circumradius."""
    mesh = make_mesh(shape)
    N = np.asarray(mesh.face_normals, dtype=np.float64)
    h = np.einsum("fi,fi->f", N, np.asarray(mesh.triangles[:, 0], dtype=np.float64))
    _, keep = np.unique(np.round(np.c_[N, h], 9), axis=0, return_index=True)
    keep = np.sort(keep)
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
    return N[keep], h[keep], radius


@functools.cache
def _round(shape: str) -> tuple[float, float, float, float, np.ndarray, float]:
    """A cone / cylinder as a solid of revolution about z: the radius ``a + b·z`` for
    ``z0 ≤ z ≤ z1``, and its side facets' outward normals ``(S, 3)`` sorted by azimuth, the first's azimuth."""
    mesh = make_mesh(shape)
    z0, z1 = float(mesh.vertices[:, 2].min()), float(mesh.vertices[:, 2].max())
    radius = float(np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1]).max())
    if shape == "cyl":
        a, b = radius, 0.0
    else:  # the apex at z1, the base (radius) at z0
        b = -radius / (z1 - z0)
        a = -b * z1
    N, _, _ = _planes(shape)
    side = N[np.abs(N[:, 2]) < 0.999]
    side = side[np.argsort(np.arctan2(side[:, 1], side[:, 0]))]
    return a, b, z0, z1, side, float(np.arctan2(side[0, 1], side[0, 0]))


def _cast_round(shape: str, R: np.ndarray, t: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`cast` for the cone and cylinder, solved as quadrics (their 360 facets are within
    7·10⁻⁵ units of the round surface) with each hit shaded by its facet's normal (flat shading)."""
    a, b, z0, z1, side, phi0 = _round(shape)
    o = -(R.T @ t)  # the camera centre and the rays in the object frame
    d = rays @ R  # (R^T d) for every ray
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    rho_o = a + b * o[2]
    A = dx * dx + dy * dy - b * b * dz * dz
    A = np.where(np.abs(A) < 1e-12, 1e-12, A)
    B = 2.0 * (o[0] * dx + o[1] * dy - b * dz * rho_o)
    C = o[0] ** 2 + o[1] ** 2 - rho_o**2
    disc = B * B - 4.0 * A * C
    sq = np.sqrt(np.clip(disc, 0.0, None))
    r1, r2 = (-B - sq) / (2.0 * A), (-B + sq) / (2.0 * A)
    r1, r2 = np.minimum(r1, r2), np.maximum(r1, r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (z0 - o[2]) / dz, (z1 - o[2]) / dz
    s0 = np.where(dz != 0, np.minimum(ta, tb), -np.inf)
    s1 = np.where(dz != 0, np.maximum(ta, tb), np.inf)
    inside_slab = (z0 <= o[2]) & (o[2] <= z1)
    s0 = np.where((dz == 0) & ~inside_slab, np.inf, s0)
    pos = A > 0  # inside the quadric between the roots; else outside them (two nappes)
    lo_a, hi_a = np.maximum(s0, r1), np.minimum(s1, r2)
    lo_b, hi_b = s0, np.minimum(s1, r1)
    lo_c, hi_c = np.maximum(s0, r2), s1
    use_b = hi_b > lo_b
    lo = np.where(pos, lo_a, np.where(use_b, lo_b, lo_c))
    hi = np.where(pos, hi_a, np.where(use_b, hi_b, hi_c))
    real = (disc >= 0) | ~pos
    whole = (disc < 0) & ~pos  # the quadric holds the whole line
    lo, hi = np.where(whole, s0, lo), np.where(whole, s1, hi)
    hit = real & (lo < hi) & (lo > 0)
    z = np.where(hit, lo, 0.0)
    p = o[None, :] + z[:, None] * d
    cap = np.isclose(lo, s0, rtol=0.0, atol=1e-9)
    k = np.rint((np.arctan2(p[:, 1], p[:, 0]) - phi0) / (2.0 * np.pi / len(side))).astype(np.int64) % len(
        side
    )
    n_obj = side[k]
    n_cap = np.zeros_like(n_obj)
    n_cap[:, 2] = np.where(np.abs(p[:, 2] - z0) < np.abs(p[:, 2] - z1), -1.0, 1.0)
    n_obj = np.where(cap[:, None], n_cap, n_obj)
    return hit, z, n_obj @ R.T


def cast(shape: str | int, R: np.ndarray, t: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Rays ``(P, 3)`` from the camera centre (``d_z = 1``) against ``shape`` at the camera-frame pose
    ``R``, ``t``: ``hit (P,)`` bool, the depth ``z (P,)`` where hit, and the entry face's camera-frame
    normal ``(P, 3)`` (module docstring)."""
    name = shape_name(shape)
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    if name in ("cone", "cyl"):
        return _cast_round(name, R, t, rays)
    N, h, _ = _planes(name)
    return cast_planes(N, h, R, t, rays)


def cast_planes(
    N: np.ndarray, h: np.ndarray, R: np.ndarray, t: np.ndarray, rays: np.ndarray
) -> tuple[np.ndarray, ...]:
    """:func:`cast` against the convex solid ``N·x ≤ h`` (object frame) at the pose ``R``, ``t``: the
    ray enters through the face of the largest ``hₖ / nₖ·d`` among those it meets from outside."""
    Nc = N @ R.T
    hc = h + Nc @ t
    nd = rays @ Nc.T
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = hc[None, :] / nd
    enter = np.where(nd < 0, tau, -np.inf)
    leave = np.where(nd > 0, tau, np.inf)
    face = enter.argmax(1)
    z = np.take_along_axis(enter, face[:, None], 1)[:, 0]
    hit = (z < leave.min(1)) & (z > 0)
    return hit, np.where(hit, z, 0.0), Nc[face]


def shade(look: Look, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Grey levels in [0, 1] of surface points ``(P, 3)`` with normals ``(P, 3)`` (camera frame) under
    ``look`` (module docstring; before gamma, blur and noise)."""
    to_light = np.asarray(look.light, dtype=np.float64) - point
    l = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)  # noqa: E741
    e = -point / np.linalg.norm(point, axis=-1, keepdims=True)
    nl = np.einsum("pi,pi->p", normal, l)
    r = 2.0 * nl[:, None] * normal - l
    spec = np.clip(np.einsum("pi,pi->p", e, r), 0.0, 1.0) ** look.shininess
    grey = look.ambient + look.diffuse * np.clip(nl, 0.0, None)
    if look.fill:
        d = -np.asarray(look.fill_direction, dtype=np.float64)
        grey = grey + look.fill * np.clip(normal @ (d / np.linalg.norm(d)), 0.0, None)
    return np.clip(look.albedo * grey + look.specular * spec, 0.0, 1.0)


class SymsolRenderer:
    """Renders the five shapes at camera-frame poses (module docstring).

    ``SymsolRenderer(image_size=224)(shape, R, t)`` → :class:`Rendered` in the paper's look;
    ``look=`` a :class:`Look` for every image, or ``render(..., look=...)`` for one. Holds no GL
    context, so it pickles and forks freely.
    """

    def __init__(self, image_size: int = 224, *, fov_deg: float = FOV_DEG, look: Look | None = None) -> None:
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
        self.look = look if look is not None else Look.paper()

    def settings(self) -> dict[str, Any]:
        """What defines the images besides the poses and the per-image looks: the scene version, the
        camera and the default look (recorded in every shard and in ``meta.json``)."""
        return {
            "scene": SCENE_VERSION,
            "image_size": self.image_size,
            "fov_deg": self.fov_deg,
            "scene_distance": SCENE_DISTANCE,
            "shading": "Open3D Phong, flat, ray cast",
            "look": self.look.to_dict(),
        }

    @functools.lru_cache(maxsize=8)  # noqa: B019 — a handful of (size, k) grids per renderer
    def _rays(self, k: int) -> np.ndarray:
        W = self.image_size
        f, c = self.K[0, 0], self.K[0, 2]
        sub = (np.arange(W * k) + 0.5) / k  # sub-pixel ray positions, pixel units
        u, v = np.meshgrid(sub, sub)
        return np.stack([(u - c) / f, (v - c) / f, np.ones_like(u)], -1)  # (Wk, Wk, 3)

    def _window(self, shape: str, t: np.ndarray, k: int) -> tuple[slice, slice]:
        """The pixel rows and columns (at ``k`` rays a pixel) the solid's bounding sphere can cover."""
        radius = _planes(shape)[2] * 1.001
        W = self.image_size
        z = float(t[2])
        if z - radius <= 1e-3:  # the sphere reaches the camera plane: every ray may hit
            return slice(0, W * k), slice(0, W * k)
        f, c = self.K[0, 0], self.K[0, 2]
        span = []
        for a in (0, 1):
            # the tangent rays of the sphere in the (a, z) plane
            dist = math.hypot(float(t[a]), z)
            ang = math.atan2(float(t[a]), z)
            half = math.asin(min(1.0, radius / dist))
            lo, hi = ang - half, ang + half
            if hi >= math.pi / 2 or lo <= -math.pi / 2:
                span.append(slice(0, W * k))
                continue
            p0 = f * math.tan(lo) + c
            p1 = f * math.tan(hi) + c
            i0 = max(0, int(math.floor(p0 * k)) - 1)
            i1 = min(W * k, int(math.ceil(p1 * k)) + 1)
            span.append(slice(i0, max(i0, i1)))
        return span[1], span[0]

    def _grey(self, shape: str, R: np.ndarray, t: np.ndarray, look: Look, k: int) -> tuple[np.ndarray, ...]:
        W = self.image_size * k
        rows, cols = self._window(shape, t, k)
        rays = self._rays(k)[rows, cols].reshape(-1, 3)
        hit, z, normal = cast(shape, R, t, rays)
        grey = np.full((W, W), look.background, dtype=np.float64)
        depth = np.zeros((W, W), dtype=np.float64)
        win = np.full(len(rays), look.background)
        if hit.any():
            win[hit] = shade(look, normal[hit], rays[hit] * z[hit, None])
        grey[rows, cols] = win.reshape(rows.stop - rows.start, cols.stop - cols.start)
        depth[rows, cols] = z.reshape(rows.stop - rows.start, cols.stop - cols.start)
        return grey, depth

    def __call__(self, shape: str | int, R: np.ndarray, t: np.ndarray, look: Look | None = None) -> Rendered:
        return self.render(shape, R, t, look)

    def render(self, shape: str | int, R: Any, t: Any, look: Look | None = None) -> Rendered:
        """Render ``shape`` at the camera-frame pose ``R`` (3, 3), ``t`` (3,) (arrays or tensors) in
        ``look`` (default: the renderer's)."""
        name = shape_name(shape)
        look = look or self.look
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        grey, depth = self._grey(name, R, t, look, 1)
        k = max(1, int(look.antialias))
        if k > 1:
            fine, _ = self._grey(name, R, t, look, k)
            grey = fine.reshape(self.image_size, k, self.image_size, k).mean((1, 3))
        if look.gamma != 1.0:
            grey = grey ** (1.0 / look.gamma)
        if look.blur > 0 or look.noise > 0:
            import cv2

            if look.blur > 0:
                sigma = look.blur * self.image_size / 224.0
                grey = cv2.GaussianBlur(grey, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REPLICATE)
            if look.noise > 0:
                grey = grey + np.random.default_rng(look.noise_seed).normal(
                    0.0, look.noise / 255.0, grey.shape
                )
        g8 = np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8)
        return Rendered(
            rgb=np.repeat(g8[..., None], 3, axis=-1),
            mask=depth > 0,
            depth=depth.astype(np.float32),
            K=self.K.copy(),
            R=R,
            t=t,
            shape_id=SHAPE_IDS[name],
        )

    def close(self) -> None:
        """Nothing to release (no GL context); kept so code written for GL renderers runs unchanged."""

    def __repr__(self) -> str:
        return f"SymsolRenderer(image_size={self.image_size}, fov_deg={self.fov_deg})"


__all__ = [
    "FOV_DEG",
    "FRUSTUM_HALF_WIDTH",
    "LOOKS",
    "MIN_IMAGE_SIZE",
    "SCENE_DISTANCE",
    "SCENE_VERSION",
    "Look",
    "Rendered",
    "SymsolRenderer",
    "cast",
    "cast_planes",
    "intrinsics",
    "prepare_gl",
    "shade",
]
