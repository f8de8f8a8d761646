"""``posediff report dir=<multirun folder>``: the jobs' metrics in one table (Table 4 layout), ``report.md``."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from ...evaluation.report import collect_sweep
from ..errors import user_input


def run(cfg: DictConfig) -> int:
    with user_input(FileNotFoundError):
        _, table = collect_sweep(str(cfg.dir))
    print(table)
    print(f"report: {Path(str(cfg.dir)) / 'report.md'}")
    return 0
