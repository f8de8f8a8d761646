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


class ImageError(ValueError):
    """An image file that cannot be a model's input (unreadable, truncated, too large, odd pixels)."""


def read_image(path: str | os.PathLike[str]):  # noqa: ANN201 - PIL.Image.Image
    """An image file, checked and decoded, as an RGB ``PIL.Image`` (square; any side).

    8-bit RGB / grey / palette images and 16-bit grey (``I;16``, scaled by 65535 — converting it the
    usual way would clip it to white) are read; alpha is dropped. Truncated files, images over
    :data:`MAX_IMAGE_PIXELS` (checked from the header, before decoding), non-square images and
    32-bit integer or float pixels are refused with one line (:class:`ImageError`).
    """
    import warnings

    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"image {p} not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(p) as im:
                w, h = im.size
                if w * h > MAX_IMAGE_PIXELS:
                    raise ImageError(
                        f"image {p} is {w}×{h} ({w * h / 1e6:.0f} megapixels), over posediff's limit of "
                        f"{MAX_IMAGE_PIXELS / 1e6:.0f} (a decompression-bomb guard); give a crop of the object"
                    )
                if w != h:
                    raise ImageError(f"image {p} is {w}×{h}; give a square crop of the object")
                im.load()
                if im.mode.startswith("I;16"):
                    grey = np.asarray(im, dtype=np.float32) / 65535.0
                    return Image.fromarray(np.round(grey * 255.0).astype(np.uint8), mode="L").convert("RGB")
                if im.mode in ("I", "F"):
                    raise ImageError(
                        f"image {p} has 32-bit {'integer' if im.mode == 'I' else 'float'} pixels; give an "
                        "8-bit (or 16-bit grey) RGB / grey image"
                    )
                return im.convert("RGB")
    except UnidentifiedImageError as e:
        raise ImageError(f"{p} is not an image PIL can read") from e
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise ImageError(f"image {p} is too large to decode safely ({e}); give a crop of the object") from e
    except OSError as e:  # truncated or corrupt data
        raise ImageError(f"image {p} is truncated or corrupt ({e}); save it again") from e


def image_tensor(image, size: int) -> Tensor:  # noqa: ANN001 - PIL.Image.Image
    """An RGB ``PIL.Image`` as ``(3, size, size)`` float in [0, 1] (bilinear resize when its side differs)."""
    from PIL import Image

    if image.width != size:
        image = image.resize((size, size), Image.BILINEAR)
    arr = np.asarray(image, dtype=np.float32) / 255.0
    return torch.from_numpy(arr.transpose(2, 0, 1).copy())


def load_image(path: str | os.PathLike[str], size: int) -> Tensor:
    """An image file as ``(3, size, size)`` float RGB in [0, 1]: :func:`read_image` (checks, one-line
    :class:`ImageError`), then :func:`image_tensor`."""
    return image_tensor(read_image(path), size)


@dataclass
class Prediction:
    """What :func:`predict` returns for one input."""

    samples: Tensor  # (N, n, n)
    modes: Any  # posediff.diffusion.Modes
    trajectory: Tensor | None = None  # (T+1, N, n, n)
    seconds: float = 0.0


@torch.no_grad()
def predict(
    module: Any,
    cond: Tensor,
    *,
    num_samples: int = 1000,
    trajectory: bool = False,
    seed: int = 0,
    mode_radius_deg: float = 10.0,
    min_mode_weight: float = 0.01,
) -> Prediction:
    """``num_samples`` hypotheses for one input ``cond`` (no batch dimension) and their modes."""
    import time

    from ..diffusion import modes

    gen = torch.Generator(device=module.device).manual_seed(int(seed))
    start = time.perf_counter()
    out = module.sample(
        cond.unsqueeze(0).to(module.device), int(num_samples), generator=gen, trajectory=trajectory
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
    "MAX_IMAGE_PIXELS",
    "ImageError",
    "image_tensor",
    "load_image",
    "read_image",
    "overlay",
    "predict",
    "save_prediction",
]
