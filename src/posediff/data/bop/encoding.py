"""The pose the network learns for a crop, and its exact inverse: the scale-invariant translation
(SITE) of CDPN / GDR-Net that the authors' code uses (``../shared/docs/reference-implementation.md``
§9.5), with the offset over the crop side where the authors divide by the box width / height.

For an object at ``R``, ``t`` (mm, camera frame) seen in a crop with centre ``c`` (pixels), side ``s``
and zoom ``r = out / s``, with ``o = π(K t)`` the projection of the object's origin:

* translation ``δ = ((o_x − c_x)/s, (o_y − c_y)/s, t_z / r)`` — the offset of the projected centre
  from the crop centre relative to the crop size, and the depth at which the object would appear at
  the crop's scale — then standardised per axis, ``(δ − mean) / std``, with statistics computed from the
  training split (:meth:`PoseEncoding.fit_stats`; the authors hard-code T-LESS constants);
* rotation ``R`` (egocentric) or ``Q(t)·R`` (allocentric), ``Q(t)`` the rotation by the smallest angle
  taking the viewing ray ``t/‖t‖`` onto the optical axis ``(0, 0, 1)``: objects that look the same in
  their crops get the same allocentric rotation, wherever they are in the image.

Inverse (:meth:`PoseEncoding.decode`): ``δ = δ̂·std + mean``; ``t_z = δ_z·r``;
``(u, v) = c + s·(δ_x, δ_y)``; ``t = t_z·K⁻¹(u, v, 1)``; ``R = Q(t)ᵀ·R_allo`` with the decoded ``t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

ROTATIONS = ("allocentric", "egocentric")


def allocentric_rotation(t: Tensor, eps: float = 1e-12) -> Tensor:
    """``Q(t) (…, 3, 3)``: the rotation by the smallest angle taking ``t/‖t‖`` onto ``(0, 0, 1)``.

    With ``a = t̂ × ẑ`` (``‖a‖ = sin θ``) and ``cos θ = t̂_z``, Rodrigues gives
    ``Q = I + [a]× + [a]×² / (1 + cos θ)``, exact and smooth except at ``t̂ = −ẑ`` (behind the camera)."""
    t = torch.as_tensor(t)
    n = t / t.norm(dim=-1, keepdim=True).clamp_min(eps)
    z = torch.zeros_like(n)
    z[..., 2] = 1.0
    a = torch.linalg.cross(n, z, dim=-1)
    c = n[..., 2]
    O = torch.zeros_like(n[..., 0])
    ax = torch.stack(
        [
            torch.stack([O, -a[..., 2], a[..., 1]], -1),
            torch.stack([a[..., 2], O, -a[..., 0]], -1),
            torch.stack([-a[..., 1], a[..., 0], O], -1),
        ],
        -2,
    )
    eye = torch.eye(3, dtype=t.dtype, device=t.device).expand_as(ax)
    return eye + ax + (ax @ ax) / (1.0 + c).clamp_min(eps)[..., None, None]


@dataclass
class PoseEncoding:
    """Encodes camera-frame poses of crops for the network and decodes its samples (module docstring).

    Args:
        rotation: ``"allocentric"`` (the authors') or ``"egocentric"``.
        mean, std: per-axis statistics of the raw ``δ`` (``None`` until :meth:`fit_stats` or given).
    """

    rotation: str = "allocentric"
    mean: Sequence[float] | None = None
    std: Sequence[float] | None = None
    _m: Tensor = field(init=False, repr=False)
    _s: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.rotation not in ROTATIONS:
            raise ValueError(
                f"unknown rotation parameterisation {self.rotation!r}; choose one of: {', '.join(ROTATIONS)}"
            )
        if (self.mean is None) != (self.std is None):
            raise ValueError("give both translation statistics (mean and std) or neither")
        if self.std is not None and (len(self.std) != 3 or min(self.std) <= 0 or len(self.mean) != 3):
            raise ValueError(
                f"translation statistics need 3 means and 3 positive stds, got {self.mean}, {self.std}"
            )

    @property
    def fitted(self) -> bool:
        return self.mean is not None

    def stats(self) -> dict[str, list[float]]:
        """``{"mean": [3], "std": [3]}`` (for configs and checkpoints)."""
        if not self.fitted:
            raise RuntimeError("translation statistics are not set: call fit_stats on the training split")
        return {"mean": [float(v) for v in self.mean], "std": [float(v) for v in self.std]}

    def _ms(self, like: Tensor) -> tuple[Tensor, Tensor]:
        st = self.stats()
        return (
            torch.tensor(st["mean"], dtype=like.dtype, device=like.device),
            torch.tensor(st["std"], dtype=like.dtype, device=like.device),
        )

    # ------------------------------------------------------------------ translation
    @staticmethod
    def raw_translation(t: Tensor, K: Tensor, centre: Tensor, side: Tensor, out: int) -> Tensor:
        """Un-standardised ``δ (…, 3)`` of translations ``t (…, 3)`` (mm) in crops ``centre (…, 2)``, ``side (…)``."""
        p = (K @ t[..., None])[..., 0]
        o = p[..., :2] / p[..., 2:3]
        side = side[..., None]
        return torch.cat([(o - centre) / side, t[..., 2:3] * side / out], dim=-1)

    def fit_stats(self, raw: Tensor) -> PoseEncoding:
        """Set the statistics from raw ``δ (N, 3)`` of the training split; returns self."""
        raw = torch.as_tensor(raw, dtype=torch.float64)
        if raw.ndim != 2 or raw.shape[-1] != 3 or raw.shape[0] < 2:
            raise ValueError(
                f"translation statistics need at least 2 training instances, got {tuple(raw.shape)}"
            )
        self.mean = raw.mean(0).tolist()
        self.std = raw.std(0).clamp_min(1e-6).tolist()
        return self

    # ------------------------------------------------------------------ both
    def encode(
        self, R: Tensor, t: Tensor, K: Tensor, centre: Tensor, side: Tensor, out: int
    ) -> tuple[Tensor, Tensor]:
        """``(R_net (…, 3, 3), δ̂ (…, 3))`` of camera-frame poses ``R (…, 3, 3)``, ``t (…, 3)`` mm."""
        m, s = self._ms(t)
        delta = (self.raw_translation(t, K, centre, side, out) - m) / s
        if self.rotation == "allocentric":
            R = allocentric_rotation(t) @ R
        return R, delta

    def decode(
        self, R_net: Tensor, delta: Tensor, K: Tensor, centre: Tensor, side: Tensor, out: int
    ) -> tuple[Tensor, Tensor]:
        """Camera-frame ``(R (…, 3, 3), t (…, 3) mm)`` of network poses; ``K``, ``centre``, ``side``
        broadcast against the leading dimensions (e.g. ``(B, 1, …)`` for ``(B, N)`` samples)."""
        m, s = self._ms(delta)
        raw = delta * s + m
        side = side[..., None]
        uv = centre + raw[..., :2] * side
        tz = raw[..., 2:3] * out / side
        ray = torch.linalg.solve(K, torch.cat([uv, torch.ones_like(tz)], -1)[..., None])[..., 0]
        t = ray / ray[..., 2:3] * tz
        return self.camera_rotation(R_net, t), t

    def camera_rotation(self, R_net: Tensor, t: Tensor) -> Tensor:
        """The camera-frame rotation of network rotations ``R_net (…, 3, 3)`` at translations ``t (…, 3)``."""
        if self.rotation == "allocentric":
            return allocentric_rotation(t).transpose(-1, -2) @ R_net
        return R_net

    def decode_pose(
        self, x: Tensor, K: Tensor, centre: Tensor, side: Tensor, out: int, translation: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """:meth:`decode` of network poses ``x`` (``[R_net | δ̂]`` (…, 4, 4)); a rotation-only model's
        ``R_net`` (…, 3, 3) needs the camera-frame ``translation`` (e.g. the true one), which it keeps."""
        if x.shape[-1] == 4:
            return self.decode(x[..., :3, :3], x[..., :3, 3], K, centre, side, out)
        if translation is None:
            raise ValueError("a rotation-only pose decodes at a given translation")
        return self.camera_rotation(x, translation), translation


__all__ = ["ROTATIONS", "PoseEncoding", "allocentric_rotation"]
