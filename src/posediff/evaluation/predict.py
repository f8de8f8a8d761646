"""Pose hypotheses for one image, their modes, and the pictures (``posediff predict``).

:func:`load_image` reads an image file (one-line errors for a missing file or a non-image),
:func:`predict` samples ``N`` hypotheses (optionally the whole denoising trajectory) and clusters
them into weighted modes (:func:`posediff.diffusion.modes`), and :func:`save_prediction` writes

* ``poses.npz`` — ``samples (N, n, n)``, ``mode_poses (K, n, n)``, ``mode_weights (K,)``,
  ``labels (N,)`` and, with a trajectory, ``trajectory (T+1, N, n, n)``;
* ``poses.json`` — the modes (rotation, translation, weight) and the settings;
* ``so3.png`` — the Mollweide SO(3) plot in the Implicit-PDF style (yaw/pitch position, roll
  colour), samples as dots, modes as weighted discs, ground truth (every equivalent pose) as circles;
* ``translations.png`` — x–y and x–z scatters of the sampled translations (groups with one);
* ``overlay.png`` — the input with the top modes drawn over it: the object's wire-frame when the
  shape is known, else coordinate axes (needs the camera ``K``);
* ``trajectory.png`` — the samples at a few levels from the prior to the end (the paper's Fig. 1).

All files are written atomically (temporary name, then rename).
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import viz
from .._io import atomic_write_bytes, atomic_write_text
from ..viz import save_figure

#: The most pixels :func:`load_image` decodes (a decompression-bomb guard; PIL's own limit is 4× more).
MAX_IMAGE_PIXELS = 50_000_000
#: How far outside [0, 1] a float image's pixels may be (one grey level: resampling overshoot and
#: rounding); :func:`image_input` refuses more (a 0–255 or a mean/std-normalised image).
IMAGE_RANGE_SLACK = 1.0 / 255.0


class ImageError(ValueError):
    """An image (a file or a tensor) that cannot be a model's input (unreadable, truncated, too large,
    not a regular file, odd pixels, wrong shape or range)."""


class ImageNotFoundError(FileNotFoundError):
    """An image path that names nothing (after ``~`` expansion)."""


class PredictArgumentError(ValueError):
    """A bad argument of :func:`predict` (``num_samples``, ``seed``, the mode settings)."""


class NonFiniteWeightsError(ValueError):
    """A module whose parameters or buffers hold NaN or ±inf (:func:`check_finite_weights`)."""


def image_path(path: str | os.PathLike[str]) -> Path:
    """``path`` with ``~`` expanded, checked to be a regular file: one line otherwise —
    :class:`ImageNotFoundError` when nothing is there, :class:`ImageError` for a folder or a device,
    pipe or socket (``/dev/null``, ``/dev/zero``: reading those never gives an image, or never ends)."""
    p = Path(os.fspath(path)).expanduser()
    if not p.exists():
        raise ImageNotFoundError(f"image {p} not found")
    if p.is_dir():
        raise ImageError(
            f"image {p} is a folder, not an image file; give one image file (e.g. {p / 'name.png'})"
        )
    if not p.is_file():
        raise ImageError(f"image {p} is not a regular file (a device, pipe or socket); give an image file")
    return p


def _upright(im):  # noqa: ANN001, ANN202 - PIL.Image.Image
    """``im`` turned as its EXIF ``Orientation`` tag says (2-8, the way viewers show it; the tag is then
    removed, so a second call does nothing); ``im`` itself without such a tag. Like viewers, an
    orientation outside 1-8 or EXIF data PIL cannot parse leave the picture as stored."""
    import struct

    from PIL import ExifTags, ImageOps

    try:
        orientation = im.getexif().get(ExifTags.Base.Orientation, 1)
    except (SyntaxError, ValueError, TypeError, KeyError, IndexError, struct.error):  # damaged metadata
        return im
    if orientation not in range(2, 9):
        return im
    return ImageOps.exif_transpose(im)


def _rgb(im, name: str):  # noqa: ANN001, ANN202 - PIL.Image.Image
    """An 8-bit RGB copy of ``im``: 16-bit grey scaled by 65535 (converting it the usual way would clip
    it to white), alpha dropped; 32-bit integer / float pixels refused."""
    from PIL import Image

    if im.mode == "RGB":
        return im
    if im.mode.startswith("I;16"):
        grey = np.asarray(im, dtype=np.float32) / 65535.0
        return Image.fromarray(np.round(grey * 255.0).astype(np.uint8), mode="L").convert("RGB")
    if im.mode in ("I", "F"):
        raise ImageError(
            f"{name} has 32-bit {'integer' if im.mode == 'I' else 'float'} pixels; give an "
            "8-bit (or 16-bit grey) RGB / grey image"
        )
    return im.convert("RGB")


def read_image(path: str | os.PathLike[str]):  # noqa: ANN201 - PIL.Image.Image
    """An image file, checked and decoded, as an upright RGB ``PIL.Image`` (square; any side).

    ``~`` is expanded; a folder, a device or anything else that is not a regular file is refused
    (:func:`image_path`). The EXIF orientation (a phone's JPEG) is applied first, as a viewer shows
    the picture. 8-bit RGB / grey / palette images and 16-bit grey (``I;16``, scaled by 65535) are
    read; alpha is dropped. Truncated files, images over :data:`MAX_IMAGE_PIXELS` (checked from the
    header, before decoding), non-square images and 32-bit integer or float pixels are refused with
    one line (:class:`ImageError`).
    """
    import warnings

    from PIL import Image, UnidentifiedImageError

    p = image_path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(p) as im:
                w, h = im.size  # the stored size; the orientation only swaps it
                if w * h > MAX_IMAGE_PIXELS:
                    raise ImageError(
                        f"image {p} is {w}×{h} ({w * h / 1e6:.0f} megapixels), over posediff's limit of "
                        f"{MAX_IMAGE_PIXELS / 1e6:.0f} (a decompression-bomb guard); give a crop of the object"
                    )
                if w != h:
                    raise ImageError(f"image {p} is {w}×{h}; give a square crop of the object")
                im.load()
                return _rgb(_upright(im), f"image {p}")
    except UnidentifiedImageError as e:
        raise ImageError(f"{p} is not an image PIL can read") from e
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise ImageError(f"image {p} is too large to decode safely ({e}); give a crop of the object") from e
    except PermissionError as e:
        raise ImageError(f"image {p} cannot be read (permission denied); make it readable") from e
    except OSError as e:  # truncated or corrupt data
        raise ImageError(f"image {p} is truncated or corrupt ({e}); save it again") from e


def image_tensor(image, size: int) -> Tensor:  # noqa: ANN001 - PIL.Image.Image
    """A ``PIL.Image`` as ``(3, size, size)`` float RGB in [0, 1]: upright by its EXIF orientation
    (a no-op for :func:`read_image`'s, already turned), made RGB, bilinear resize when its side
    differs; a non-square image is refused (:class:`ImageError`)."""
    from PIL import Image

    image = _rgb(_upright(image), "the image")
    if image.width != image.height:
        raise ImageError(f"the image is {image.width}×{image.height}; give a square crop of the object")
    if image.width != size:
        image = image.resize((size, size), Image.BILINEAR)
    arr = np.asarray(image, dtype=np.float32) / 255.0
    return torch.from_numpy(arr.transpose(2, 0, 1).copy())


def load_image(path: str | os.PathLike[str], size: int) -> Tensor:
    """An image file as ``(3, size, size)`` float RGB in [0, 1]: :func:`read_image` (checks, one-line
    :class:`ImageError`), then :func:`image_tensor`."""
    return image_tensor(read_image(path), size)


def image_input(
    image: Any, *, size: int | None = None, dtype: torch.dtype = torch.float32, name: str = "image"
) -> Tensor:
    """The one image :func:`predict` takes, checked and made ``(3, H, W)`` float ``dtype`` in [0, 1].

    Accepted: a tensor (or NumPy array) ``(3, H, W)`` or a batch of one ``(1, 3, H, W)``; float of any
    precision (converted) with values in [0, 1] (:data:`IMAGE_RANGE_SLACK` allowed each side), or
    ``uint8`` 0–255 (scaled by 1/255); a ``PIL.Image`` (:func:`image_tensor`). Refused with one line
    (:class:`ImageError`): a batch of several images (call :func:`predict` per image, or
    ``module.sample(images, N)`` for raw batched samples), channels-last or grey layouts, other
    integer or bool pixels, non-finite pixels, a float image outside [0, 1] (0–255: divide by 255;
    mean/std-normalised: give the raw image — the encoder normalises), and a side other than
    ``size`` (the model's input side, when given)."""
    if not isinstance(image, (Tensor, np.ndarray)) and hasattr(image, "getexif") and hasattr(image, "mode"):
        if size is None:
            raise ImageError(
                f"{name} is a PIL image but the model's input side is unknown; use image_tensor(image, size)"
            )
        image = image_tensor(image, size)
    if isinstance(image, np.ndarray):
        if image.dtype == object or not (np.issubdtype(image.dtype, np.number) or image.dtype == np.bool_):
            raise ImageError(
                f"{name} is a NumPy array of {image.dtype}; give a (3, H, W) float or uint8 tensor"
            )
        image = torch.from_numpy(np.ascontiguousarray(image))
    if not isinstance(image, Tensor):
        raise ImageError(
            f"{name} must be a (3, H, W) tensor, got {type(image).__name__}; read a file with "
            "posediff.load_image(path, size)"
        )
    shape = tuple(image.shape)
    if image.ndim == 4:
        if shape[0] != 1:
            raise ImageError(
                f"{name} is a batch of {shape[0]} images {shape}; posediff.sample takes one image: call it once "
                "per image (module.sample(images, N) samples a batch without the modes)"
            )
        image = image[0]
    if image.ndim != 3 or image.shape[0] != 3:
        if image.ndim == 3 and image.shape[-1] in (3, 4) and image.shape[0] not in (3, 4):
            hint = "it looks channels-last (H, W, C): give image.permute(2, 0, 1)[:3]"
        elif image.ndim == 2 or (image.ndim == 3 and image.shape[0] == 1):
            hint = "it looks grey: give image.expand(3, H, W) (three equal channels)"
        elif image.ndim == 3 and image.shape[0] == 4:
            hint = "it has 4 channels (RGBA?): give image[:3]"
        else:
            hint = "read a file with posediff.load_image(path, size)"
        raise ImageError(f"{name} must be (3, H, W) RGB or (1, 3, H, W), got {shape}; {hint}")
    H, W = int(image.shape[1]), int(image.shape[2])
    if H == 0 or W == 0:
        raise ImageError(f"{name} is empty ({shape})")
    if size is not None and (H, W) != (int(size), int(size)):
        raise ImageError(
            f"{name} is {H}×{W} pixels; this model takes {size}×{size}: resize it "
            f"(posediff.load_image(path, size={size}) does)"
        )
    if image.dtype == torch.uint8:
        return image.to(dtype) / 255.0
    if image.dtype == torch.bool or not (image.is_floating_point()):
        raise ImageError(f"{name} has {image.dtype} pixels; give float pixels in [0, 1] or uint8 0–255")
    finite = torch.isfinite(image)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        raise ImageError(
            f"{name} has {bad} non-finite pixel value{'s' if bad > 1 else ''} (NaN or ±inf) of {image.numel()}; "
            "give a finite image in [0, 1]"
        )
    lo, hi = float(image.min()), float(image.max())
    if lo < -IMAGE_RANGE_SLACK or hi > 1.0 + IMAGE_RANGE_SLACK:
        if lo >= -IMAGE_RANGE_SLACK and hi <= 255.0 + IMAGE_RANGE_SLACK:
            hint = "it looks like 0–255: divide it by 255 (or give a uint8 tensor)"
        elif lo < 0:
            hint = "it looks normalised (mean/std): give the raw image in [0, 1] (the encoder normalises)"
        else:
            hint = "give pixels in [0, 1]"
        raise ImageError(f"{name} has float pixels in [{lo:g}, {hi:g}], not [0, 1]; {hint}")
    return image.to(dtype)


def check_finite_weights(module: Any, where: str = "the model") -> None:
    """Refuse, with one line naming the first offender, a module whose parameters or floating-point
    buffers (batch-norm statistics) hold NaN or ±inf (:class:`NonFiniteWeightsError`): such weights
    give NaN features and NaN crop boxes, which ``torchvision.ops.roi_align`` does not survive.
    ``where``: how to name the module (e.g. the checkpoint's path)."""
    import itertools

    tensors = itertools.chain(
        (("parameter", n, t) for n, t in module.named_parameters()),
        (("buffer", n, t) for n, t in module.named_buffers()),
    )
    for kind, name, t in tensors:
        if not (t.is_floating_point() or t.is_complex()) or t.numel() == 0:
            continue
        finite = torch.isfinite(t.detach())
        if not bool(finite.all()):
            bad = int((~finite).sum())
            raise NonFiniteWeightsError(
                f"{where}: {kind} {name} has {bad} non-finite value{'s' if bad > 1 else ''} (NaN or ±inf) of "
                f"{t.numel()}; the weights are corrupt (a diverged run or a damaged file): use another checkpoint"
            )


def _whole_number(value: Any, name: str, least: int, most: int | None = None) -> int:
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if isinstance(value, Tensor) and value.numel() == 1 and not value.is_floating_point():
        value, ok = int(value), value.dtype != torch.bool
    if not ok or value < least or (most is not None and value > most):
        span = f"[{least}, {most}]" if most is not None else f"≥ {least}"
        raise PredictArgumentError(f"{name} must be a whole number {span}, got {value!r}")
    return int(value)


def _real(value: Any, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise PredictArgumentError(f"{name} must be a number, got {value!r}")
    return float(value)


def check_predict_arguments(
    num_samples: Any, seed: Any, mode_radius_deg: Any, min_mode_weight: Any, trajectory: Any = False
) -> tuple[int, int, float, float, bool]:
    """:func:`predict`'s settings checked (one-line :class:`PredictArgumentError` naming the
    argument): ``num_samples`` a whole number ≥ 1, ``seed`` a whole number (a 64-bit seed),
    ``mode_radius_deg`` finite and > 0, ``min_mode_weight`` in [0, 1), ``trajectory`` a bool."""
    n = _whole_number(num_samples, "num_samples", 1)
    s = _whole_number(seed, "seed", -(2**63), 2**64 - 1)
    radius = _real(mode_radius_deg, "mode_radius_deg")
    if not (math.isfinite(radius) and radius > 0):
        raise PredictArgumentError(
            f"mode_radius_deg must be finite and > 0 (degrees), got {mode_radius_deg!r}"
        )
    weight = _real(min_mode_weight, "min_mode_weight")
    if not 0.0 <= weight < 1.0:
        raise PredictArgumentError(
            f"min_mode_weight must be in [0, 1) (a fraction of the samples), got {min_mode_weight!r}"
        )
    if not isinstance(trajectory, (bool, np.bool_)):
        raise PredictArgumentError(f"trajectory must be True or False, got {trajectory!r}")
    return n, s, radius, weight, bool(trajectory)


@dataclass
class Prediction:
    """What :func:`predict` returns for one input."""

    samples: Tensor  # (N, n, n)
    modes: Any  # posediff.diffusion.Modes
    trajectory: Tensor | None = None  # (T+1, N, n, n)
    seconds: float = 0.0


def _takes_images(module: Any) -> tuple[bool, int | None]:
    """Whether ``module`` is conditioned on images, and its encoder's input side when it says."""
    encoder = getattr(module, "encoder", None)
    size = getattr(encoder, "image_size", None)
    size = int(size) if isinstance(size, (int, np.integer)) and not isinstance(size, bool) else None
    return getattr(module, "cond_key", None) == "image" or size is not None, size


def _module_dtype(module: Any) -> torch.dtype:
    for p in module.parameters():
        if p.is_floating_point():
            return p.dtype
    return torch.float32


@torch.no_grad()
def predict(
    module: Any,
    cond: Any,
    *,
    num_samples: int = 1000,
    trajectory: bool = False,
    seed: int = 0,
    mode_radius_deg: float = 10.0,
    min_mode_weight: float = 0.01,
) -> Prediction:
    """``num_samples`` hypotheses for ONE input ``cond`` and their modes (``posediff.sample``).

    For an image model ``cond`` is one image, checked before anything runs (:func:`image_input`):
    ``(3, H, W)`` or a batch of one ``(1, 3, H, W)``, float in [0, 1] (any precision; converted to the
    model's) or ``uint8`` 0–255 (scaled by 1/255), finite, of the model's side. A batch of several
    images is refused (call once per image). For other models ``cond`` is one condition without a
    batch dimension (finite when float). The arguments are checked by
    :func:`check_predict_arguments` and the module's weights by :func:`check_finite_weights`; every
    refusal is one line (a ``ValueError`` subclass)."""
    import time

    from ..diffusion import modes

    num_samples, seed, mode_radius_deg, min_mode_weight, trajectory = check_predict_arguments(
        num_samples, seed, mode_radius_deg, min_mode_weight, trajectory
    )
    images, size = _takes_images(module)
    dtype = _module_dtype(module)
    if images:
        cond = image_input(cond, size=size, dtype=dtype)
    elif isinstance(cond, Tensor) and cond.is_floating_point() and not bool(torch.isfinite(cond).all()):
        raise PredictArgumentError(f"the condition {tuple(cond.shape)} has non-finite values (NaN or ±inf)")
    check_finite_weights(module, "the model")
    gen = torch.Generator(device=module.device).manual_seed(seed)
    start = time.perf_counter()
    out = module.sample(
        cond.unsqueeze(0).to(module.device), num_samples, generator=gen, trajectory=trajectory
    )
    seconds = time.perf_counter() - start
    x, path = out if trajectory else (out, None)
    x = x[0].double().cpu()
    m = modes(x, module.group, radius_deg=mode_radius_deg, min_weight=min_mode_weight)
    return Prediction(
        samples=x,
        modes=m,
        trajectory=None if path is None else path[:, 0].double().cpu(),
        seconds=seconds,
    )


def decode_prediction(
    pred: Prediction,
    decode: Any,
    group: Any,
    *,
    mode_radius_deg: float = 10.0,
    mode_translation_radius: float = 20.0,
    min_mode_weight: float = 0.01,
) -> Prediction:
    """The prediction in another frame: ``decode(poses (..., n, n)) → (R (..., 3, 3), t (..., 3))``
    maps the network's poses (e.g. a BOP crop's ``[R_allo | δ]``) to camera-frame ``[R | t]``
    (4 × 4); the modes are found again there (``mode_translation_radius`` in the units of ``t``)."""
    from ..diffusion import modes
    from ..lie import get_group

    def to_camera(x: Tensor) -> Tensor:
        R, t = decode(x)
        out = torch.zeros((*R.shape[:-2], 4, 4), dtype=torch.float64)
        out[..., :3, :3], out[..., :3, 3], out[..., 3, 3] = R, t, 1.0
        return out

    samples = to_camera(pred.samples)
    target = group if group.matrix_dim == 4 else get_group("r3so3")
    m = modes(samples, target, radius_deg=mode_radius_deg, translation_radius=mode_translation_radius,
              min_weight=min_mode_weight)  # fmt: skip
    path = None if pred.trajectory is None else to_camera(pred.trajectory)
    return Prediction(samples=samples, modes=m, trajectory=path, seconds=pred.seconds)


def _rt(poses: Tensor) -> tuple[np.ndarray, np.ndarray | None]:
    P = poses.numpy()
    return P[..., :3, :3], (P[..., :3, 3] if P.shape[-1] == 4 else None)


# The pictures of a Prediction: thin wrappers over posediff.viz.prediction (plain arrays).
def figure_so3(pred: Prediction, gt_rotations: np.ndarray | None = None, title: str = "") -> Any:
    return viz.figure_so3(pred.samples.numpy(), pred.modes.poses.numpy(), pred.modes.weights.numpy(),
                          gt_rotations=gt_rotations, title=title)  # fmt: skip


def figure_translations(pred: Prediction, gt_translation: np.ndarray | None = None) -> Any:
    return viz.figure_translations(pred.samples.numpy()[:, :3, 3], gt_translation)


def overlay(
    image: Tensor,
    poses: Tensor,
    K: np.ndarray,
    *,
    camera_offset: np.ndarray | None = None,
    shape: str | None = None,
    mesh: Any = None,
    scale: int = 4,
) -> np.ndarray:
    """:func:`posediff.viz.overlay` with the wire-frame of the SYMSOL ``shape`` or of a trimesh ``mesh``
    (e.g. a BOP model in mm, with ``K`` the crop's intrinsics), else coordinate axes."""
    if shape is not None and mesh is None:
        from ..data.symsol import make_mesh

        mesh = make_mesh(shape)
    edges, length = viz.mesh_edges(mesh) if mesh is not None else (None, 1.0)
    return viz.overlay(image.numpy(), poses.numpy(), K, edges=edges, axis_length=length,
                       camera_offset=camera_offset, scale=scale)  # fmt: skip


def figure_trajectory(pred: Prediction, panels: int = 5, gt_rotations: np.ndarray | None = None) -> Any:
    """The samples at ``panels`` evenly spaced points of the trajectory (prior → result)."""
    if pred.trajectory is None:
        raise ValueError("no trajectory: predict(..., trajectory=True) first")
    return viz.figure_trajectory(pred.trajectory.numpy(), panels, gt_rotations)


def save_prediction(
    pred: Prediction,
    out_dir: str | os.PathLike[str],
    *,
    image: Tensor | None = None,
    K: np.ndarray | None = None,
    camera_offset: np.ndarray | None = None,
    shape: str | None = None,
    mesh: Any = None,
    gt_pose: Tensor | None = None,
    gt_rotations: np.ndarray | None = None,
    top_modes: int = 3,
    info: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write the files listed in the module docstring into ``out_dir``; returns name → path.
    ``gt_rotations (E, 3, 3)``: the ground truth's equivalent rotations (default: from ``shape``'s
    symmetries, or the ground truth alone); ``mesh``: the object model for the overlay."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    arrays = {
        "samples": pred.samples.numpy(),
        "mode_poses": pred.modes.poses.numpy(),
        "mode_weights": pred.modes.weights.numpy(),
        "labels": pred.modes.labels.numpy(),
    }
    if pred.trajectory is not None:
        arrays["trajectory"] = pred.trajectory.float().numpy()
    if gt_pose is not None:
        arrays["gt_pose"] = gt_pose.double().numpy()
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    files["npz"] = atomic_write_bytes(out / "poses.npz", buf.getvalue())
    Rm, tm = _rt(pred.modes.poses)
    doc = {
        **(info or {}),
        "num_samples": int(pred.samples.shape[0]),
        "seconds": pred.seconds,
        "modes": [
            {
                "weight": float(pred.modes.weights[k]),
                "rotation": Rm[k].tolist(),
                **({"translation": tm[k].tolist()} if tm is not None else {}),
            }
            for k in range(len(pred.modes))
        ],
        "modes_summary": pred.modes.summary(),
    }
    files["json"] = atomic_write_text(out / "poses.json", json.dumps(doc, indent=2) + "\n")
    gt_R = gt_t = None
    if gt_pose is not None:
        gt_R = gt_pose[:3, :3].double()
        gt_t = gt_pose[:3, 3].double().numpy() if gt_pose.shape[-1] == 4 else None
        if gt_rotations is not None:
            gt_R = torch.as_tensor(gt_rotations, dtype=torch.float64)
        elif shape is not None:
            from ..data.symsol import equivalent_poses

            gt_R = equivalent_poses(shape, gt_R, step_deg=10.0)
        gt_R = gt_R.reshape(-1, 3, 3).numpy()
    files["so3"] = save_figure(figure_so3(pred, gt_R, title=pred.modes.summary()), out / "so3.png", dpi=110)
    if pred.samples.shape[-1] == 4:
        files["translations"] = save_figure(
            figure_translations(pred, gt_t), out / "translations.png", dpi=110
        )
    if image is not None and K is not None and len(pred.modes):
        import cv2

        img = overlay(
            image, pred.modes.poses[:top_modes], K, camera_offset=camera_offset, shape=shape, mesh=mesh
        )
        ok, png = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        assert ok
        files["overlay"] = atomic_write_bytes(out / "overlay.png", png.tobytes())
    if pred.trajectory is not None:
        files["trajectory"] = save_figure(
            figure_trajectory(pred, gt_rotations=gt_R), out / "trajectory.png", dpi=110
        )
    return files


__all__ = [
    "Prediction",
    "decode_prediction",
    "figure_so3",
    "figure_trajectory",
    "figure_translations",
    "IMAGE_RANGE_SLACK",
    "MAX_IMAGE_PIXELS",
    "ImageError",
    "ImageNotFoundError",
    "NonFiniteWeightsError",
    "PredictArgumentError",
    "check_finite_weights",
    "check_predict_arguments",
    "image_input",
    "image_path",
    "image_tensor",
    "load_image",
    "read_image",
    "overlay",
    "predict",
    "save_prediction",
]
