"""``posediff groups``: the registered Lie groups and their tensor layouts."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from ...lie import LieGroup
from ..errors import fail


def run(args: list[str]) -> int:
    if args:
        return fail("posediff", f"groups takes no arguments, got {' '.join(args)}")
    table = Table(title="registered Lie groups")
    for col in ("name", "class", "element", "tangent", "order"):
        table.add_column(col)
    for name, cls in sorted(LieGroup.registry.items()):
        n = cls.matrix_dim
        table.add_row(
            name,
            f"{cls.__module__}.{cls.__qualname__}",
            f"(*b, {n}, {n})",
            f"(*b, {cls.dim})",
            tangent_order(cls),
        )
    Console().print(table)
    return 0


def tangent_order(cls: type[LieGroup]) -> str:
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
