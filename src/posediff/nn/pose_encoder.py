"""``PoseEncoder``: an image encoder that also estimates one pose — the *anchor* — and, optionally,
looks at an object-centred crop (locate, then crop).

Beyond the paper (issue "orientation from images in minutes"). The paper's encoder
(:class:`~posediff.nn.ResNetEncoder`) turns the whole image into a feature; on SYMSOL-T at CPU scale
that feature is dominated by *where* the object is, and orientation is slow to appear. This encoder
adds two levers, each one switch away:

* **A pose head.** A linear map of the feature to a rotation (the 6-D representation made a
  rotation by Gram–Schmidt, :func:`rotation_from_6d`) and a translation. Its output is the anchor
  ``X̂`` the anchored denoiser works relative to (``Log(X̂⁻¹X̃)``), and the estimate of the regression
  baselines (paper Table 2, "Regression" / "Iterative regression").
* **Locate-then-crop** (``crop_size`` set, groups with a translation). A small CNN on the whole image
  (with pixel-coordinate channels, so position is easy for it) regresses the translation; the crop
  is the square around that translation's projection whose side covers a sphere of
  ``crop_margin · object_radius`` scene units at the scene centre's depth, resampled to ``crop_size`` pixels
  (``torchvision.ops.roi_align``); the ResNet sees only the crop. In training the crop is placed by
  the ground-truth translation plus Gaussian jitter (``crop_jitter`` scene units, the locator's
  expected error), at test by the locator — the RoI idea of the BOP pipeline with a learned locator.
  The rotation head then predicts the **allocentric** rotation (how the object looks in the crop)
  and the anchor is ``R̂ = R_ray · R̂_allo``, ``R_ray`` the rotation taking the optical axis to the
  ray through the crop centre (up to ~10° on SYMSOL-T's frustum). The crop's translation (scene
  frame) is appended to the feature and is the anchor's translation, refined by the head.

Camera: SYMSOL-T's pinhole (``fov_deg`` horizontal field of view, principal point at the image
centre, scene centre ``scene_distance`` in front of the camera; translations are relative to it, as
the data's ``pose``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..symmetry import (
    SHAPES,
    decode_embedding,
    embedding_dim,
    invariant_embedding,
    standardise_embedding,
    unstandardise_embedding,
)
from .encoder import ResNetEncoder

#: the rotation heads: a 6-D rotation (Gram–Schmidt), or symmetry-invariant embeddings per shape
ROTATION_HEADS = ("6d", "invariant")
#: where the depth comes from: regressed (None), or the apparent size for the locator and the pose head
#: ("size") or the pose head only ("size_head")
DEPTH_CUES = (None, "size", "size_head")
#: how the depth cue measures the object's image area (PoseEncoder ``area_estimate``)
AREA_ESTIMATES = ("threshold", "coverage", "filled")
#: what predicts the depth offset from the apparent size (PoseEncoder ``depth_head``)
DEPTH_HEADS = ("linear", "embedding")


def coverage_area(grey: Tensor, background_level: float = 0.05) -> Tensor:
    """The object's image area as a fraction of the image, ``(B, H, W)`` grey in [0, 1] → ``(B,)``, for
    a lit object on a black background: a pixel brighter than half ``background_level`` is object;
    one with no background among its 8 neighbours counts whole; an edge pixel counts by its covered
    fraction, its grey level over the brightest inner pixel within 1 (else 2) pixels — an
    antialiased edge pixel's value is its coverage times the shade of the face it shows."""
    g = grey[:, None]
    fg = (g > 0.5 * background_level).to(g.dtype)
    near_background = F.max_pool2d(1.0 - fg, 3, 1, 1)
    inner = fg * (1.0 - near_background)
    shade = F.max_pool2d(g * inner, 3, 1, 1)
    shade = torch.where(shade > 0, shade, F.max_pool2d(g * inner, 5, 1, 2))
    edge = fg * near_background
    covered = torch.where(shade > 0, (g / shade.clamp_min(1e-6)).clamp(0.0, 1.0), torch.ones_like(g))
    return (inner + edge * covered).mean((-3, -2, -1))


def filled_area(grey: Tensor, contrast: float = 0.05) -> Tensor:
    """The object's image area as a fraction of the image, ``(B, H, W)`` grey in [0, 1] → ``(B,)``,
    for a convex object, however dark its faces: the background level is the median of the image's
    border; a pixel differing from it by more than ``contrast``, in a 2 × 2 block of such pixels (so
    that pixel noise is not), is object; the silhouette is then
    filled along rows and along columns (a pixel between the first and last object pixel of its row,
    or of its column, counts), so faces shaded as dark as the background inside the outline count, and
    a grey background or a dimmer light leaves the area where it was (a face *at* the outline as dark
    as the background is lost: nothing in the pixels tells it apart)."""
    B, H, W = grey.shape
    border = torch.cat([grey[:, 0], grey[:, -1], grey[:, 1:-1, 0], grey[:, 1:-1, -1]], dim=1)
    background = border.median(dim=1).values
    raw = ((grey - background[:, None, None]).abs() > contrast).to(grey.dtype)[:, None]
    # opened by a 2 × 2 square: a pixel counts when it lies in a 2 × 2 block of such pixels, so isolated
    # noise (and noise beside the outline) drops out while the outline and its corners stay put
    eroded = 1.0 - F.max_pool2d(1.0 - raw, 2, stride=1)
    fg = F.max_pool2d(F.pad(eroded, (1, 1, 1, 1)), 2, stride=1)[:, 0] > 0
    cols = torch.arange(W, device=grey.device)
    rows = torch.arange(H, device=grey.device)

    def span(mask: Tensor, idx: Tensor) -> Tensor:  # (B, L, N) → bool, between first and last True
        big = mask.shape[-1]
        first = torch.where(mask, idx, big).amin(-1, keepdim=True)
        last = torch.where(mask, idx, -1).amax(-1, keepdim=True)
        return (idx >= first) & (idx <= last)

    filled = span(fg, cols) | span(fg.transpose(1, 2), rows).transpose(1, 2)
    return filled.to(grey.dtype).mean((-2, -1))


#: the invariant head's targets: the raw embedding, or centred and scaled to one spread per shape
EMBEDDING_SCALES = ("raw", "haar")
#: the children of a torchvision ResNet that form the trunk (all but avgpool and fc), in order
_TORCHVISION_TRUNK = ("conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4")

__all__ = ["CropBoxError", "Encoding", "PoseEncoder", "ray_rotation", "rotation_from_6d"]


class CropBoxError(ValueError):
    """The crop around the located object cannot be placed: its position is NaN or ±inf (a NaN
    image or NaN locator weights). Raised before ``torchvision.ops.roi_align``, which would crash."""


def rotation_from_6d(x: Tensor) -> Tensor:
    """``(…, 6)`` → ``(…, 3, 3)``: the first two columns by Gram–Schmidt, the third their cross
    product (Zhou et al.'s continuous 6-D representation). Columns ``a₁, a₂`` = ``x[..., :3]``,
    ``x[..., 3:]``."""
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = nn.functional.normalize(a1, dim=-1, eps=1e-8)
    b2 = nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1, eps=1e-8)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def ray_rotation(t: Tensor) -> Tensor:
    """``(…, 3)`` camera-frame points → ``(…, 3, 3)``: the smallest rotation taking the optical axis
    ``(0, 0, 1)`` to the direction of ``t`` (Rodrigues about ``ẑ × t̂``); ``R_ray = I`` on the axis."""
    d = nn.functional.normalize(t, dim=-1)
    x, y, c = d[..., 0], d[..., 1], d[..., 2]
    # axis k = ẑ × d = (−y, x, 0); R = I + [k]× + [k]×² / (1 + c)  (valid for c > −1)
    k = 1.0 / (1.0 + c)
    one = torch.ones_like(c)
    rows = [
        one - k * x * x, -k * x * y, x,
        -k * x * y, one - k * y * y, y,
        -x, -y, c,
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


@dataclass
class Encoding:
    """What :class:`PoseEncoder` returns: the denoiser's ``feature (B, F)``, the anchor's
    ``rotation (B, 3, 3)`` and ``translation (B, 3)`` (scene frame; ``None`` for rotation-only), and
    the locator's own estimate ``located (B, 3)`` (``None`` without a crop), trained by regression;
    ``crop_translation`` / ``ray`` the crop's translation and ray rotation (``None`` without a crop);
    ``embedding`` / ``shape_logits`` the invariant head's outputs (``None`` for the 6-D head);
    ``log_size`` the apparent-size depth cue ``(B,)`` (with a ``depth_cue``, else ``None``)."""

    feature: Tensor
    rotation: Tensor
    translation: Tensor | None = None
    located: Tensor | None = None
    crop_translation: Tensor | None = None
    ray: Tensor | None = None
    embedding: Tensor | None = None
    shape_logits: Tensor | None = None
    log_size: Tensor | None = None


class _Locator(nn.Module):
    """Where the object is: a small fully convolutional network (RGB + pixel-coordinate channels, two
    stride-2 convolutions) whose one-channel heat map at 1/4 resolution is read out by a spatial
    soft-argmax as the projected centre ``(u, v)``, and whose pooled features regress the depth
    offset from the scene centre; back-projected to the scene-frame translation. The soft-argmax
    is translation-equivariant, so the position is learned in a few hundred steps."""

    def __init__(
        self, image_size: int, width: int, focal: float, scene_distance: float, size_depth: bool = False
    ) -> None:
        super().__init__()
        #: depth from apparent size (``z = z₀·exp(½(log_size + δ))``, δ learned) instead of a linear offset
        self.size_depth = bool(size_depth)
        w = int(width)
        self.convs = nn.Sequential(
            nn.Conv2d(5, w // 2, 3, stride=2, padding=1), nn.BatchNorm2d(w // 2), nn.ReLU(inplace=True),
            nn.Conv2d(w // 2, w, 3, stride=2, padding=1), nn.BatchNorm2d(w), nn.ReLU(inplace=True),
            nn.Conv2d(w, w, 3, padding=1), nn.BatchNorm2d(w), nn.ReLU(inplace=True),
        )  # fmt: skip
        self.heat = nn.Conv2d(w, 1, 1)
        self.depth = nn.Linear(w, 1)
        nn.init.zeros_(self.depth.weight)
        nn.init.zeros_(self.depth.bias)
        self.image_size, self.focal, self.scene_distance = (
            int(image_size),
            float(focal),
            float(scene_distance),
        )
        lin = torch.linspace(-1.0, 1.0, self.image_size)
        yy, xx = torch.meshgrid(lin, lin, indexing="ij")
        self.register_buffer("coords", torch.stack([xx, yy])[None], persistent=False)

    def forward(self, image: Tensor, log_size: Tensor | None = None) -> Tensor:
        h = self.convs(torch.cat([image, self.coords.expand(image.shape[0], -1, -1, -1)], dim=1))
        b, _, hh, ww = h.shape
        prob = self.heat(h).flatten(1).softmax(-1).view(b, hh, ww)
        # pixel centres of the heat map, in input pixels
        xs = (torch.arange(ww, device=h.device, dtype=h.dtype) + 0.5) * (self.image_size / ww)
        ys = (torch.arange(hh, device=h.device, dtype=h.dtype) + 0.5) * (self.image_size / hh)
        u = (prob.sum(1) * xs).sum(-1)
        v = (prob.sum(2) * ys).sum(-1)
        dz = self.depth(h.mean((-2, -1)))[:, 0]
        if self.size_depth and log_size is not None:
            z = self.scene_distance * torch.exp(0.5 * (log_size + dz))
            dz = z - self.scene_distance
        else:
            z = self.scene_distance + dz
        c = self.image_size / 2.0
        return torch.stack([(u - c) / self.focal * z, (v - c) / self.focal * z, dz], dim=-1)


class PoseEncoder(nn.Module):
    """``(B, 3, H, W)`` images in [0, 1] → :class:`Encoding` (feature + anchor pose).

    Args:
        arch, out_dim, head_channels, weights: the ResNet trunk and feature head, as
            :class:`~posediff.nn.ResNetEncoder` (``weights``: a local state dict, never downloaded;
            a ``posediff pretrain`` file or a torchvision one).
        image_size: side of the input images.
        translation: whether poses have a translation (``se3`` / ``r3so3``; ``False`` for ``so3``).
        crop_size: ``None`` — the trunk sees the whole image (the paper); an int — locate, then crop
            to ``crop_size`` pixels (needs ``translation``).
        object_radius: radius (scene units) of the sphere the crop must hold (SYMSOL: 3.03, the
            cube's half diagonal, the largest shape).
        crop_margin: the crop side is ``2 · crop_margin · object_radius`` scene units at the scene
            centre's depth, whatever the object's depth (1.15: an object at the near end of SYMSOL-T's
            ±1 depth range still fits); only the centre follows the translation.
        crop_jitter: std (scene units; one, or x / y / z) of the Gaussian jitter of training crops
            around the truth — about the locator's error (its depth, from apparent size, is the coarsest).
        fov_deg, scene_distance: the camera (module docstring).
        locator_width: channels of the locator's second convolution.
        depth_cue: ``None`` — the depth is regressed like x and y; ``"size"`` (beyond the paper; scenes
            on a dark background, as SYMSOL-T) — from the object's apparent size: its image area ``a``
            (the fraction of pixels brighter than ``background_level``, edge pixels fractional) falls
            as ``1/z²``, so ``z = z₀·exp(½(log a_ref − log a))`` with ``log a_ref`` the running mean
            of ``log a`` (training) plus a learned offset — the locator's from its pooled features, the
            pose head's from the crop's (which see the shape and its orientation, on which the area at
            ``z₀`` depends); the crop's x and y follow its ray to that depth. ``"size_head"``: the pose
            head's depth only, the locator's regressed as without a cue. Linear offsets need weights
            far larger than Adam at 1e-4 moves in thousands of steps (the depth signal is a few percent
            of the pooled features); this parameterisation has the physics and learns only ``a_ref``.
        background_level: the grey level (0–1) below which a pixel is background (with a ``depth_cue``).
        area_estimate: how the apparent size's area is measured (with a ``depth_cue``): ``"threshold"``
            — every pixel brighter than ``background_level`` counts whole, dimmer ones by their grey
            level (on antialiased renders 3.8 % ± 1.1 % above the silhouette's true area: a depth
            noise of ~0.5 %); ``"coverage"`` — pixels away from the background count whole, each edge
            pixel by its grey level over its brightest inner neighbour's, its covered fraction
            (0.997 ± 0.004 of the true area on SYMSOL-T; :func:`coverage_area`); ``"filled"`` — the
            silhouette against the image's own background level, filled along rows and columns
            (:func:`filled_area`): dark faces, the light's strength and the background level leave it
            unchanged.
        depth_head: the depth offset δ (with a ``depth_cue``): ``"linear"`` — the pose head's third
            translation output, linear in the crop's feature; ``"embedding"`` (with
            ``rotation_head="invariant"``) — plus a small MLP of the head's own (detached) invariant
            embeddings, shape logits and ``log_size``: the apparent area at a given depth depends on
            the orientation only through what the symmetries leave of it, which the embedding is.
        rotation_head: ``"6d"`` (a rotation by Gram–Schmidt, trained by ``min_S ‖R̂ − R·S‖²``) or
            ``"invariant"`` (beyond the paper, SYMSOL shapes): per shape the symmetry-invariant
            embedding φ(R_allo) of :func:`~posediff.symmetry.invariant_embedding` plus shape logits,
            regressed by squared error — a continuous target, where a rotation picked out of the
            equivalence class jumps; the rotation is decoded from it (no gradient).
        shapes: the shapes the invariant head covers (its classifier's classes).
        embedding_scale: the invariant head's targets: ``"raw"`` (φ as
            :func:`~posediff.symmetry.invariant_embedding` gives it) or ``"haar"`` (centred and scaled to
            the same spread for every shape, :func:`~posediff.symmetry.standardise_embedding`: the raw
            icosahedron's φ varies 7× less than the tetrahedron's and 18× less than the cone's, so in a
            loss summed over shapes it had almost no weight). Decoding undoes the scaling.
    """

    def __init__(
        self,
        arch: str = "resnet18",
        out_dim: int = 256,
        *,
        image_size: int = 224,
        head_channels: int = 32,
        weights: str | os.PathLike[str] | None = None,
        translation: bool = True,
        crop_size: int | None = None,
        object_radius: float = 3.04,
        crop_margin: float = 1.15,
        crop_jitter: float | Sequence[float] = (0.1, 0.1, 0.4),
        fov_deg: float = 60.0,
        scene_distance: float = 5.25 / math.tan(math.radians(30.0)),
        locator_width: int = 32,
        depth_cue: str | None = None,
        background_level: float = 0.05,
        area_estimate: str = "threshold",
        depth_head: str = "linear",
        rotation_head: str = "6d",
        shapes: Sequence[str] = SHAPES,
        embedding_scale: str = "raw",
    ) -> None:
        super().__init__()
        if rotation_head not in ROTATION_HEADS:
            raise ValueError(
                f"unknown rotation_head {rotation_head!r}; choose one of: {', '.join(ROTATION_HEADS)}"
            )
        if embedding_scale not in EMBEDDING_SCALES:
            raise ValueError(
                f"unknown embedding_scale {embedding_scale!r}; choose one of: {', '.join(EMBEDDING_SCALES)}"
            )
        self.rotation_head, self.embedding_scale = rotation_head, embedding_scale
        self.shapes = tuple(str(x) for x in shapes)
        unknown = [x for x in self.shapes if x not in SHAPES]
        if rotation_head == "invariant" and (unknown or not self.shapes):
            raise ValueError(
                f"rotation_head=invariant covers the SYMSOL shapes {SHAPES}; got shapes={list(shapes)}"
            )
        if depth_cue not in DEPTH_CUES:
            raise ValueError(f"unknown depth_cue {depth_cue!r}; choose one of: null, size, size_head")
        if depth_cue is not None and crop_size is None:
            raise ValueError(
                f"depth_cue={depth_cue} needs locate-then-crop (crop_size set); without a crop set encoder.depth_cue=null"
            )
        if not 0.0 < float(background_level) < 1.0:
            raise ValueError(f"background_level must be in (0, 1), got {background_level}")
        if area_estimate not in AREA_ESTIMATES:
            raise ValueError(
                f"unknown area_estimate {area_estimate!r}; choose one of: {', '.join(AREA_ESTIMATES)}"
            )
        self.depth_cue, self.background_level = depth_cue, float(background_level)
        self.area_estimate = area_estimate
        if depth_head not in DEPTH_HEADS:
            raise ValueError(f"unknown depth_head {depth_head!r}; choose one of: {', '.join(DEPTH_HEADS)}")
        if depth_head == "embedding" and (rotation_head != "invariant" or depth_cue is None):
            raise ValueError(
                "depth_head=embedding needs rotation_head=invariant and a depth_cue (size or size_head); "
                "otherwise set encoder.depth_head=linear"
            )
        self.depth_head = depth_head
        if depth_cue is not None:  # the running mean of log a over training images (NaN: none seen yet)
            self.register_buffer("log_area_mean", torch.tensor(float("nan")))
        #: decode the invariant head's rotation in training too (the anchored denoiser needs it)
        self.decode_in_training = True
        if crop_size is not None and not translation:
            raise ValueError(
                "crop_size needs poses with a translation (se3 / r3so3); use crop_size=null for so3"
            )
        self.image_size, self.out_dim = int(image_size), int(out_dim)
        self.translation, self.crop_size = bool(translation), None if crop_size is None else int(crop_size)
        self.object_radius, self.crop_margin = float(object_radius), float(crop_margin)
        jitter = (
            [float(crop_jitter)] * 3
            if isinstance(crop_jitter, (int, float))
            else [float(j) for j in crop_jitter]
        )
        if len(jitter) != 3 or min(jitter) < 0:
            raise ValueError(f"crop_jitter must be one std or three (x, y, z) stds >= 0, got {crop_jitter}")
        self.register_buffer("crop_jitter", torch.tensor(jitter), persistent=False)
        self.focal = (self.image_size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
        self.scene_distance = float(scene_distance)
        trunk_size = self.crop_size or self.image_size
        base = ResNetEncoder(arch, out_dim, image_size=trunk_size, head_channels=head_channels)
        self.arch = arch
        self.trunk = base.trunk
        self.register_buffer("mean", base.mean.clone(), persistent=False)
        self.register_buffer("std", base.std.clone(), persistent=False)
        channels = base.head[0].in_channels
        side = -(-trunk_size // 32)
        geometry = (3 if self.crop_size is not None else 0) + (1 if depth_cue is not None else 0)
        self.reduce = nn.Sequential(
            nn.Conv2d(channels, head_channels, 1), nn.ReLU(inplace=True), nn.Flatten()
        )
        self.dense = nn.Linear(head_channels * side * side + geometry, self.out_dim)
        # the invariant head: one slice per shape (its embedding), then one logit per shape
        self._slices: dict[str, tuple[int, int]] = {}
        width = 6
        if rotation_head == "invariant":
            width = 0
            for name in self.shapes:
                self._slices[name] = (width, width + embedding_dim(name))
                width += embedding_dim(name)
            width += len(self.shapes)
        self.rotation_width = width
        self.pose_head = nn.Linear(self.out_dim, width + (3 if self.translation else 0))
        with torch.no_grad():  # start at the identity rotation (6-D head) and zero translation
            self.pose_head.weight.mul_(0.1)
            self.pose_head.bias.zero_()
            if rotation_head == "6d":
                self.pose_head.bias[:6] = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
        self.depth_mlp: nn.Module | None = None
        if depth_head == "embedding":
            self.depth_mlp = nn.Sequential(
                nn.Linear(width + 1, 64), nn.SiLU(), nn.Linear(64, 64), nn.SiLU(), nn.Linear(64, 1)
            )
            with torch.no_grad():  # starts as the linear head alone
                self.depth_mlp[-1].weight.zero_()
                self.depth_mlp[-1].bias.zero_()
        self.locator = (
            _Locator(self.image_size, locator_width, self.focal, self.scene_distance, depth_cue == "size")
            if self.crop_size is not None
            else None
        )
        if weights is not None:
            self.load_weights(weights)

    def load_weights(self, path: str | os.PathLike[str]) -> None:
        """Start from a local file (never a download): a ``posediff pretrain`` file or any posediff
        checkpoint (its encoder's weights — trunk, head, pose head, locator, whatever matches), or a
        torchvision ResNet state dict (the trunk only). Read with ``weights_only=True``; a missing
        file or one that fits nothing is a one-line error."""
        from pathlib import Path

        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(
                f"encoder weights file {p} not found (posediff never downloads; make one with "
                f"`posediff pretrain`, or give a local torchvision {self.arch} state dict, or weights=null)"
            )
        state = torch.load(p, map_location="cpu", weights_only=True)
        if isinstance(state, dict) and "state_dict" in state:  # a Lightning checkpoint
            state = state["state_dict"]
        if isinstance(state, dict) and "encoder_state_dict" in state:  # a posediff pretrain file
            state = state["encoder_state_dict"]
        if not isinstance(state, dict):
            raise ValueError(f"{p} holds no state dict")
        if any(k.startswith("encoder.") for k in state):
            state = {k[len("encoder.") :]: v for k, v in state.items() if k.startswith("encoder.")}
        if not any(k.startswith("trunk.") for k in state):  # torchvision: conv1, bn1, layer1, ... (no fc)
            # the trunk is the net's children but avgpool and fc, as ResNetEncoder builds it
            names = [*_TORCHVISION_TRUNK]
            state = {
                f"trunk.{names.index(k.split('.')[0])}.{k.split('.', 1)[1]}": v
                for k, v in state.items()
                if k.split(".")[0] in names
            }
        own = self.state_dict()
        fits = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
        if not any(k.startswith("trunk.") for k in fits):
            raise ValueError(f"{p}: no trunk weights fit this {self.arch} encoder")
        self.load_state_dict(fits, strict=False)

    # ------------------------------------------------------------------ geometry
    def project(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """Scene-frame translations ``(B, 3)`` → crop boxes ``(B, 4)`` (x1, y1, x2, y2 in pixels) and
        the camera-frame centres ``(B, 3)``."""
        t_cam = t + t.new_tensor([0.0, 0.0, self.scene_distance])
        z = t_cam[:, 2].clamp_min(1e-3)
        c = self.image_size / 2.0
        u, v = self.focal * t_cam[:, 0] / z + c, self.focal * t_cam[:, 1] / z + c
        # a fixed side (the sphere at the scene centre's depth): the crop's scale never depends on an
        # estimated depth, whose error (the locator's ~5 %) cost more than the ±11 % of true depth
        half = torch.full_like(z, self.focal * self.crop_margin * self.object_radius / self.scene_distance)
        return torch.stack([u - half, v - half, u + half, v + half], dim=-1), t_cam

    def crop(self, image: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """The object-centred crops ``(B, 3, crop_size, crop_size)`` around scene translations ``t``
        and the rays' rotations ``R_ray (B, 3, 3)``."""
        from torchvision.ops import roi_align

        boxes, t_cam = self.project(t)
        if not bool(torch.isfinite(boxes).all()):  # roi_align crashes the process (SIGSEGV) on NaN boxes
            raise CropBoxError(
                "the located object position is not finite (NaN or ±inf): the image or the locator's "
                "weights hold NaN/inf; check the input image and the checkpoint"
            )
        rois = torch.cat([torch.arange(len(t), device=t.device, dtype=t.dtype)[:, None], boxes], dim=1)
        out = roi_align(image, rois.to(image.dtype), (self.crop_size, self.crop_size), 1.0, 2, True)
        return out, ray_rotation(t_cam)

    # ------------------------------------------------------------------ forward
    def forward(self, image: Tensor, pose: Tensor | None = None) -> Encoding:
        """Encode ``image``; ``pose`` (the training target, ``(B, n, n)``) places training crops."""
        if image.shape[-2:] != (self.image_size, self.image_size):
            raise ValueError(
                f"encoder built for {self.image_size}×{self.image_size} images, got {tuple(image.shape[-2:])}"
            )
        located = None
        ray = None
        extra: list[Tensor] = []
        x = image
        log_size = self.log_size(image) if self.depth_cue is not None else None
        if self.locator is not None:
            located = self.locator(image, log_size)
            if self.training and pose is not None:
                t0 = pose[:, :3, 3].to(image.dtype)
                t_crop = t0 + self.crop_jitter * torch.randn_like(t0)
            else:
                t_crop = located.detach()
            x, ray = self.crop(image, t_crop)
            extra.append(t_crop)
        f = self.reduce(self.trunk((x - self.mean) / self.std))
        t_crop = extra[0] if extra else None
        if log_size is not None:
            extra.append(log_size[:, None].to(f.dtype))
        feature = self.dense(torch.cat([f, *extra], dim=1) if extra else f)
        rotation, translation, embedding, logits = self.head_pose(feature, ray, t_crop, log_size)
        return Encoding(feature, rotation, translation, located, t_crop, ray, embedding, logits, log_size)

    def log_size(self, image: Tensor) -> Tensor:
        """The apparent-size cue ``(B,)``: ``log a_ref − log a``, ``a`` the image's object area (the
        fraction of pixels brighter than ``background_level``; edge pixels count by their grey level)
        and ``log a_ref`` its running mean over training images (updated in training mode, kept in the
        state dict), so that ``z₀·exp(½·log_size)`` is the depth of an average object of that size."""
        grey = image.float().mean(1)
        if self.area_estimate == "coverage":
            area = coverage_area(grey, self.background_level).clamp_min(1e-4)
        elif self.area_estimate == "filled":
            area = filled_area(grey, self.background_level).clamp_min(1e-4)
        else:
            area = (grey / self.background_level).clamp(0.0, 1.0).mean((-2, -1)).clamp_min(1e-4)
        log_area = area.log()
        mean = self.log_area_mean
        batch_mean = log_area.detach().mean()
        if self.training:
            with torch.no_grad():  # no data-dependent branch: the first batch's mean, then a running mean
                mean.copy_(torch.where(torch.isnan(mean), batch_mean, mean.lerp(batch_mean, 0.01)))
        ref = torch.where(torch.isnan(mean), batch_mean, mean)
        return ref - log_area

    def head_pose(
        self,
        feature: Tensor,
        ray: Tensor | None = None,
        crop_translation: Tensor | None = None,
        log_size: Tensor | None = None,
    ) -> tuple[Tensor | None, Tensor | None, Tensor | None, Tensor | None]:
        """The pose head on a feature: rotation ``(B, 3, 3)`` (egocentric: ``R_ray · R_allo`` with a
        crop), translation ``(B, 3)`` (the crop's plus the head's offset; ``None`` for rotation-only),
        and for the invariant head its embeddings ``(B, D)`` and shape logits ``(B, K)`` (the rotation
        is then decoded for the most likely shape, without gradient; ``None`` in training unless
        :attr:`decode_in_training`). With ``log_size`` (a ``depth_cue``) the depth is
        ``z₀·exp(½(log_size + δ))``, δ the head's third translation output, and the crop's x, y are moved
        along its ray to that depth before the head's x, y offsets. Called on a detached feature it is
        a linear probe."""
        head = self.pose_head(feature)
        embedding = logits = None
        if self.rotation_head == "6d":
            rotation: Tensor | None = rotation_from_6d(head[:, :6])
        else:
            embedding = head[:, : self.rotation_width - len(self.shapes)]
            logits = head[:, self.rotation_width - len(self.shapes) : self.rotation_width]
            rotation = None
            if not self.training or self.decode_in_training:
                rotation = self.decode(embedding, logits)
        if ray is not None and rotation is not None:
            rotation = ray @ rotation
        translation = None
        if self.translation:
            w = self.rotation_width
            offset = head[:, w : w + 3]
            if log_size is not None and crop_translation is not None:
                z0 = self.scene_distance
                delta = offset[:, 2]
                if self.depth_mlp is not None:
                    cue = torch.cat(
                        [head[:, : self.rotation_width].detach(), log_size[:, None].to(head.dtype)], 1
                    )
                    delta = delta + self.depth_mlp(cue)[:, 0]
                z_cam = z0 * torch.exp(0.5 * (log_size.to(offset.dtype) + delta))
                along_ray = crop_translation[:, :2] * (z_cam / (crop_translation[:, 2] + z0))[:, None]
                translation = torch.cat([along_ray + offset[:, :2], (z_cam - z0)[:, None]], dim=1)
            else:
                translation = offset + (crop_translation if crop_translation is not None else 0.0)
        return rotation, translation, embedding, logits

    def decode(self, embedding: Tensor, logits: Tensor, **kw: int) -> Tensor:
        """The (allocentric) rotations of invariant-head outputs: each input decoded
        (:func:`~posediff.symmetry.decode_embedding`) with the embedding of its most likely shape."""
        best = logits.detach().argmax(-1)
        out = torch.eye(3, dtype=embedding.dtype, device=embedding.device).repeat(len(embedding), 1, 1)
        for k in best.unique().tolist():
            sel = best == k
            name = self.shapes[int(k)]
            i, j = self._slices[name]
            if self.training and "rounds" not in kw:  # in training a coarser search (12° … 3°) is enough
                kw = {**kw, "rounds": 3}
            phi = embedding[sel, i:j]
            if self.embedding_scale == "haar":
                phi = unstandardise_embedding(name, phi.detach())
            out[sel] = decode_embedding(name, phi, **kw)
        return out

    def embedding_loss(self, enc: Encoding, shape_ids: Tensor, R_gt: Tensor) -> Tensor:
        """The invariant head's symmetry-aware loss per input ``(B,)``: the squared error of the true
        shape's embedding against ``φ(R_allo)`` of the ground truth (``R_allo = R_rayᵀ R``), plus the
        cross-entropy of the shape logits. ``shape_ids`` index :data:`~posediff.symmetry.SHAPES`."""
        if enc.embedding is None or enc.shape_logits is None:
            raise ValueError(
                "embedding_loss needs an encoding of the invariant head (rotation_head=invariant)"
            )
        R = R_gt.to(enc.embedding.dtype)
        if enc.ray is not None:
            R = enc.ray.mT @ R
        pos = torch.tensor([self.shapes.index(SHAPES[int(k)]) if SHAPES[int(k)] in self.shapes else -1
                            for k in shape_ids.tolist()], device=shape_ids.device)  # fmt: skip
        if bool((pos < 0).any()):
            raise ValueError(f"the invariant head covers {list(self.shapes)}; the batch has other shapes")
        loss = nn.functional.cross_entropy(enc.shape_logits, pos, reduction="none")
        for k in pos.unique().tolist():
            sel = pos == k
            name = self.shapes[int(k)]
            i, j = self._slices[name]
            target = invariant_embedding(name, R[sel])
            if self.embedding_scale == "haar":
                target = standardise_embedding(name, target)
            loss[sel] = loss[sel] + (enc.embedding[sel, i:j] - target).square().sum(-1)
        return loss

    def extra_repr(self) -> str:
        return (
            f"arch={self.arch}, image_size={self.image_size}, out_dim={self.out_dim}, crop_size={self.crop_size}, "
            f"translation={self.translation}"
        )
