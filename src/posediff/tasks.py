"""The composition root: the only place where objects are built from config and wired together.

Each function here backs one ``posediff`` subcommand; ``posediff.cli`` only parses arguments.
"""

import sys

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from rich.console import Console
from rich.table import Table

from .lie import LieGroup
from .testing import LIE_GROUP_CHECKS


def list_groups() -> int:
    """``posediff groups``: the registered Lie groups and their tensor layouts."""
    table = Table(title="registered Lie groups")
    for col in ("name", "class", "element", "tangent", "order"):
        table.add_column(col)
    for name, cls in sorted(LieGroup.registry.items()):
        order = _tangent_order(cls)
        n = cls.matrix_dim
        table.add_row(
            name, f"{cls.__module__}.{cls.__qualname__}", f"(*b, {n}, {n})", f"(*b, {cls.dim})", order
        )
    Console().print(table)
    return 0


def _tangent_order(cls: type[LieGroup]) -> str:
    """``[ρ(3), φ(3)]``: the runs of translation (ρ) and rotation (φ) components of the tangent."""
    rot = range(cls.dim)[cls.rotation_slice]
    labels = ["φ" if i in rot else "ρ" for i in range(cls.dim)]
    runs: list[list[str | int]] = []
    for lab in labels:
        if runs and runs[-1][0] == lab:
            runs[-1][1] = int(runs[-1][1]) + 1
        else:
            runs.append([lab, 1])
    return "[" + ", ".join(f"{lab}({k})" for lab, k in runs) + "]"


def check_group(cfg: DictConfig) -> int:
    """``posediff check``: run the Lie group contract on ``instantiate(cfg.group)``."""
    group = instantiate(cfg.group)
    if not isinstance(group, LieGroup):
        raise TypeError(f"group config builds {type(group).__name__}, not a posediff LieGroup")
    names = list(cfg.checks) if cfg.checks is not None else list(LIE_GROUP_CHECKS)
    unknown = [n for n in names if n not in LIE_GROUP_CHECKS]
    if unknown:
        print(
            f"posediff check: unknown check(s) {unknown}; available: {', '.join(LIE_GROUP_CHECKS)}",
            file=sys.stderr,
        )
        return 2
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
            first = str(e).strip().splitlines()[0] if str(e).strip() else "failed"
            kind = "" if isinstance(e, AssertionError) else f"{type(e).__name__}: "
            table.add_row(name, f"[red]FAIL[/red] {kind}{first}")
    Console().print(table)
    print(f"{group.name}: {len(names) - failed}/{len(names)} checks passed")
    return 1 if failed else 0
