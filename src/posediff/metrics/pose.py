"""Distribution metrics for sampled poses against a symmetric ground truth.

Shapes: ``R_samples (…, N, 3, 3)`` are N samples (hypotheses) per ground truth ``R_gt (…, 3, 3)``;
usually ``…`` is a batch ``B``. The set of poses equivalent to ``R_gt`` is ``{R_gt·S}`` with S in
the object's symmetries — a :class:`posediff.symmetry.SymmetrySet` (symmetry on the right), or a
SYMSOL shape name for its exact group. Angles reported in degrees unless the name says otherwise.

Memory: the discrete-shape metrics build one ``(…, N, S)`` trace tensor (plus the gathered best
``(…, N, 3, 3)`` rotations), e.g. 8·1000·60 floats, never ``(…, N, S, 3, 3)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..symmetry import SymmetrySet, as_symmetry_set

#: what the symmetry argument of every metric accepts: a set, or a SYMSOL shape name
Symmetries = SymmetrySet | str


def rotation_errors_deg(shape: Symmetries, R_samples: Tensor, R_gt: Tensor) -> Tensor:
    """Per sample, the smallest angle (degrees) to the equivalent set of ``R_gt``:
    ``(…, N, 3, 3), (…, 3, 3) → (…, N)`` (:meth:`SymmetrySet.min_angle_deg`). Exact for the SYMSOL
    cone / cylinder."""
    R_samples, R_gt = torch.as_tensor(R_samples), torch.as_tensor(R_gt)
    return as_symmetry_set(shape).min_angle_deg(R_samples, R_gt)


def rotation_spread_deg(shape: Symmetries, R_samples: Tensor, R_gt: Tensor) -> Tensor:
    """The paper's "spread": mean over the N samples of :func:`rotation_errors_deg`,
    ``(…, N, 3, 3), (…, 3, 3) → (…,)``."""
    return rotation_errors_deg(shape, R_samples, R_gt).mean(-1)


def translation_errors(t_samples: Tensor, t_gt: Tensor) -> Tensor:
    """Per sample, the Euclidean distance to the ground truth: ``(…, N, 3), (…, 3) → (…, N)``
    (in the units of ``t``; all symmetric equivalents share the translation)."""
    t_samples, t_gt = torch.as_tensor(t_samples), torch.as_tensor(t_gt)
    return (t_samples - t_gt.unsqueeze(-2)).norm(dim=-1)


def translation_error(t_samples: Tensor, t_gt: Tensor) -> Tensor:
    """Mean over the N samples of :func:`translation_errors`: ``(…, N, 3), (…, 3) → (…,)``."""
    return translation_errors(t_samples, t_gt).mean(-1)


def mode_coverage(shape: Symmetries, R_samples: Tensor, R_gt: Tensor, threshold_deg: float = 5.0) -> Tensor:
    """Fraction of the discrete equivalent poses ``R_gt·S`` that have at least one sample strictly
    within ``threshold_deg`` degrees. ``(…, N, 3, 3), (…, 3, 3) → (…,)`` in [0, 1].

    Continuous symmetries (cone, cylinder) have no finite set of modes: the result is all NaN (same
    dtype and batch shape), so it can be averaged with ``nanmean`` next to the polyhedra.
    """
    R_samples, R_gt = torch.as_tensor(R_samples), torch.as_tensor(R_gt)
    batch = torch.broadcast_shapes(R_samples.shape[:-3], R_gt.shape[:-2])
    sym = as_symmetry_set(shape)
    if sym.is_continuous:
        return torch.full(batch, math.nan, dtype=R_samples.dtype, device=R_samples.device)
    G = torch.from_numpy(np.array(sym.rotations())).to(dtype=R_samples.dtype, device=R_samples.device)
    M = R_gt.unsqueeze(-3).mT @ R_samples  # (…, N, 3, 3)
    # angle(R_gt S, R_n) = angle(Sᵀ M_n); tr(Sᵀ M) = Σ_ij S_ij M_ij; angle < thr ⟺ tr > 1 + 2 cos thr
    traces = torch.einsum("...nij,sij->...ns", M, G)
    hit = traces > 1.0 + 2.0 * math.cos(math.radians(threshold_deg))
    return hit.any(dim=-2).to(R_samples.dtype).mean(-1)


def recall(errors: Tensor, thresholds: Sequence[float] | Tensor) -> Tensor:
    """Fraction of ``errors`` (any shape, flattened) strictly below each threshold →
    ``(len(thresholds),)``. NaN errors count as misses; no errors gives NaN."""
    errors = torch.as_tensor(errors)
    dtype = errors.dtype if errors.is_floating_point() else torch.float64
    errors = errors.reshape(-1).to(dtype)
    thr = torch.as_tensor(thresholds, dtype=dtype, device=errors.device).reshape(-1)
    if errors.numel() == 0:
        return torch.full(thr.shape, math.nan, dtype=dtype, device=errors.device)
    return (errors.unsqueeze(0) < thr.unsqueeze(1)).to(dtype).mean(-1)
