"""``posediff check group=so3``: the Lie group contract (:data:`posediff.testing.LIE_GROUP_CHECKS`) on a
group built from config; exit 1 when a check fails."""

from __future__ import annotations

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from rich.console import Console
from rich.table import Table

from ...lie import LieGroup
from ...testing import LIE_GROUP_CHECKS
from ..errors import InputError, first_line


def run(cfg: DictConfig) -> int:
    group = instantiate(cfg.group)
    if not isinstance(group, LieGroup):
        raise TypeError(f"group config builds {type(group).__name__}, not a posediff LieGroup")
    names = list(cfg.checks) if cfg.checks is not None else list(LIE_GROUP_CHECKS)
    unknown = [n for n in names if n not in LIE_GROUP_CHECKS]
    if unknown:
        raise InputError(f"unknown check(s) {unknown}; available: {', '.join(LIE_GROUP_CHECKS)}")
    device = torch.device(cfg.device)
    table = Table(title=f"contract of {group!r} on {device}")
    table.add_column("check")
    table.add_column("result")
    failed = 0
    for name in names:
        try:
            LIE_GROUP_CHECKS[name](group, device)
            table.add_row(name, "[green]ok[/green]")
        except Exception as e:  # noqa: BLE001 - every failing check is reported, none aborts the run
            failed += 1
            first = first_line(e) if str(e).strip() else "failed"
            kind = "" if isinstance(e, AssertionError) else f"{type(e).__name__}: "
            table.add_row(name, f"[red]FAIL[/red] {kind}{first}")
    Console().print(table)
    print(f"{group.name}: {len(names) - failed}/{len(names)} checks passed")
    return 1 if failed else 0
