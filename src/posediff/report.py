"""Moved to :mod:`posediff.evaluation.report`; these names stay importable from here (CHANGELOG, 0.2.0)."""

from .evaluation.report import (
    AXIS_COLUMNS,
    ReportCallback,
    axis_table,
    collect_sweep,
    run_table,
    sweep_rows,
    sweep_table,
)

__all__ = [
    "AXIS_COLUMNS",
    "ReportCallback",
    "axis_table",
    "collect_sweep",
    "run_table",
    "sweep_rows",
    "sweep_table",
]
