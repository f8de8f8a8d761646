"""Moved to :mod:`posediff.evaluation.bop`; these names stay importable from here (CHANGELOG, 0.2.0)."""

from .evaluation.bop import (
    ROT_THRESHOLDS_DEG,
    TRANS_THRESHOLDS_CM,
    best_hypothesis,
    check_estimates,
    estimates_of_predictions,
    evaluate_bop,
    predict_targets,
    score_estimates,
)

__all__ = [
    "ROT_THRESHOLDS_DEG",
    "TRANS_THRESHOLDS_CM",
    "best_hypothesis",
    "check_estimates",
    "estimates_of_predictions",
    "evaluate_bop",
    "predict_targets",
    "score_estimates",
]
