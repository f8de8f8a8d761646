"""``posediff.metrics``: evaluation metrics for pose distributions (see :mod:`posediff.metrics.pose`)."""

from .pose import mode_coverage, recall, rotation_spread_deg, translation_error

__all__ = ["rotation_spread_deg", "translation_error", "mode_coverage", "recall"]
