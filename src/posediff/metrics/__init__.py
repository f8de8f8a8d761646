"""``posediff.metrics``: evaluation metrics for pose distributions (see :mod:`posediff.metrics.pose`)."""

from .pose import (
    mode_coverage,
    recall,
    rotation_errors_deg,
    rotation_spread_deg,
    translation_error,
    translation_errors,
)

__all__ = [
    "rotation_errors_deg",
    "rotation_spread_deg",
    "translation_errors",
    "translation_error",
    "mode_coverage",
    "recall",
]
