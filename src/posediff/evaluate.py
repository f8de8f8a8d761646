"""Moved to :mod:`posediff.evaluation` (``shapes``: the per-shape scorer; ``sampling``: the shared loop);
these names stay importable from here (CHANGELOG, 0.2.0)."""

from .evaluation.sampling import SampledBatches
from .evaluation.shapes import ROTATION_THRESHOLDS_DEG, TRANSLATION_THRESHOLDS, evaluate

__all__ = ["ROTATION_THRESHOLDS_DEG", "TRANSLATION_THRESHOLDS", "SampledBatches", "evaluate"]
