"""Region-of-interest crops: the square box around an object, Dynamic Zoom-In, and the crop itself.

Dynamic Zoom-In (DZI; Li et al., CDPN, ICCV 2019, with the settings of the authors' code,
``../shared/docs/reference-implementation.md`` §9.3), for a box ``[x, y, w, h]`` with centre ``c``:

* training: centre ``c + (w·u₁, h·u₂)``, ``u ~ U[−shift, shift]``; side
  ``s = max(w, h)·(1 + scale·U[−1, 1])·pad`` (shift = scale = 0.25, pad = 1.5: 1.125–1.875 × max(w, h));
* test: centre ``c``, side ``pad·max(w, h)``;

the side is clipped to ``max(H, W)`` of the image. The ``s × s`` square is resampled to
``out × out`` (bilinear for the image, nearest for masks; outside the image is black / empty), which is
a camera with the same centre and the intrinsics :func:`crop_intrinsics` — focal length × r and
principal point ``(c_K − (centre − s/2))·r − ½``, ``r = out / s`` (the zoom; pixel centres at
integers, as OpenCV).
"""

from __future__ import annotations

import numpy as np


def dzi(
    bbox: np.ndarray,
    image_hw: tuple[int, int],
    *,
    rng: np.random.Generator | None = None,
    shift: float = 0.25,
    scale: float = 0.25,
    pad: float = 1.5,
) -> tuple[np.ndarray, float]:
    """``(centre (2,), side)`` of the square crop of ``bbox = [x, y, w, h]`` (module docstring);
    jittered when ``rng`` is given (training), centred otherwise (test)."""
    centre, side = dzi_many(bbox, np.asarray(image_hw), rng, shift=shift, scale=scale, pad=pad)
    return centre[0], float(side[0])


def dzi_many(
    bbox: np.ndarray,
    image_hw: np.ndarray,
    rng: np.random.Generator | None,
    *,
    shift: float = 0.25,
    scale: float = 0.25,
    pad: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`dzi` for ``bbox (N, 4)`` in images ``image_hw (N, 2)`` (or one ``(2,)``):
    ``(centres (N, 2), sides (N,))``."""
    bbox = np.asarray(bbox, dtype=np.float64).reshape(-1, 4)
    wh = bbox[:, 2:]
    centre = bbox[:, :2] + 0.5 * wh
    side = wh.max(axis=1)
    if rng is not None:
        centre = centre + wh * rng.uniform(-shift, shift, size=(len(bbox), 2))
        side = side * (1.0 + scale * rng.uniform(-1.0, 1.0, size=len(bbox)))
    side = np.minimum(side * pad, np.asarray(image_hw, dtype=np.float64).reshape(-1, 2).max(axis=1))
    return centre, np.maximum(side, 1.0)


def clip_boxes(bbox: np.ndarray, image_hw: np.ndarray) -> np.ndarray:
    """``[x, y, w, h]`` boxes ``(N, 4)`` clipped to their images ``image_hw (N, 2)`` (or one ``(2,)``)."""
    bbox = np.asarray(bbox, dtype=np.float64).reshape(-1, 4)
    H, W = np.asarray(image_hw, dtype=np.float64).reshape(-1, 2).T
    x1, y1 = np.clip(bbox[:, 0], 0, W), np.clip(bbox[:, 1], 0, H)
    x2, y2 = np.clip(bbox[:, 0] + bbox[:, 2], 0, W), np.clip(bbox[:, 1] + bbox[:, 3], 0, H)
    return np.stack([x1, y1, np.maximum(x2 - x1, 0.0), np.maximum(y2 - y1, 0.0)], axis=1)


def clip_box(bbox: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """``[x, y, w, h]`` clipped to the image (the authors clip the training box)."""
    return clip_boxes(bbox, np.asarray(image_hw))[0]


def crop_matrix(centre: np.ndarray, side: float, out: int) -> np.ndarray:
    """The 2×3 affine map from image pixels to crop pixels (no rotation).

    Pixel centres follow OpenCV (pixel ``i`` covers ``[i − ½, i + ½]``): the square's corner
    ``centre − s/2`` maps to the crop's corner ``−½``, and ``centre`` to the crop's centre ``(out − 1)/2``."""
    r = out / float(side)
    x0, y0 = np.asarray(centre, dtype=np.float64) - 0.5 * side
    return np.array([[r, 0.0, -r * x0 - 0.5], [0.0, r, -r * y0 - 0.5]])


def crop_intrinsics(K: np.ndarray, centre: np.ndarray, side: float, out: int) -> np.ndarray:
    """The intrinsics of the crop: ``A·K`` with ``A`` the crop's pixel map (module docstring)."""
    A = np.eye(3)
    A[:2] = crop_matrix(centre, side, out)
    return A @ np.asarray(K, dtype=np.float64)


def crop(
    image: np.ndarray, centre: np.ndarray, side: float, out: int, *, nearest: bool = False
) -> np.ndarray:
    """The ``out × out`` crop of ``image (H, W[, C])`` (bilinear, or nearest for masks)."""
    import cv2

    M = crop_matrix(centre, side, out)
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    src = image.astype(np.uint8) if image.dtype == bool else image
    res = cv2.warpAffine(src, M, (out, out), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return res.astype(bool) if image.dtype == bool else res


__all__ = ["clip_box", "clip_boxes", "crop", "crop_intrinsics", "crop_matrix", "dzi", "dzi_many"]
