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

from .bop import sphere_projections_overlap  # noqa: E402
from .bop19 import (  # noqa: E402
    BOP19,
    BopEstimate,
    ar_from_paired_errors,
    average_recall,
    pose_recalls,
    read_bop19_csv,
    write_bop19_csv,
)

__all__ += [
    "sphere_projections_overlap",
    "BOP19",
    "BopEstimate",
    "ar_from_paired_errors",
    "average_recall",
    "pose_recalls",
    "read_bop19_csv",
    "write_bop19_csv",
]
