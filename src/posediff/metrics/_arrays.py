"""Inputs of the BOP metrics as arrays: numpy arrays, torch tensors (moved to the CPU) or nested
sequences, all computed in float64."""

from typing import Any

import numpy as np


def as_float64(x: Any) -> np.ndarray:
    """numpy float64 view of ``x`` (torch tensors are detached and moved to the CPU first)."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


__all__ = ["as_float64"]
