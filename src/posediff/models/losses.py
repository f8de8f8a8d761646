"""The symmetry-aware losses both kinds of pose model train with (the anchor's auxiliary loss, the
regression baselines): ``min_S ‖R − R_gt·S‖²_F`` over the object's equivalent poses."""

import torch
from torch import Tensor

from ..symmetry import set_chordal_sq, symsol_chordal_sq


def chordal_to_angle(chordal_sq: Tensor) -> Tensor:
    """Geodesic angle (radians) of a squared chordal distance ``8 sin²(θ/2)``."""
    return 2.0 * torch.asin((chordal_sq.clamp_min(0.0) / 8.0).sqrt().clamp(max=1.0))


def symmetric_rotation_loss(batch: dict[str, Tensor], R: Tensor) -> Tensor:
    """``min_S ‖R − R_gt·S‖²_F`` per input (``(B,)``, or ``(B, N)`` for ``R (B, N, 3, 3)``) against the
    rotation of the batch's ``pose`` (the network's frame: allocentric for BOP crops) over the input's
    symmetries: the batch's padded ``symmetries`` / ``symmetries_mask`` (BOP ``models_info``) or its
    SYMSOL ``shape`` ids (exact groups, cone / cylinder in closed form)."""
    R_gt = batch["pose"][..., :3, :3].to(R.dtype)
    if "symmetries" in batch:
        return set_chordal_sq(R, R_gt, batch["symmetries"].to(R.dtype), batch["symmetries_mask"])
    if "shape" in batch:
        return symsol_chordal_sq(batch["shape"], R, R_gt)
    raise ValueError(
        "the symmetry-aware loss needs the batch's symmetries: SYMSOL shape ids ('shape') or BOP "
        "'symmetries'; this data has neither"
    )


__all__ = ["chordal_to_angle", "symmetric_rotation_loss"]
