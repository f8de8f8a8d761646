"""The package's layers, checked from the source (docs/architecture.md): the import graph of
``src/posediff`` has no cycle, and every import points down the layers — never up, never sideways."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "posediff"

#: the parts of posediff, bottom first; a part imports only parts of lower levels (and itself)
LEVELS: dict[str, int] = {
    "_registry": 0, "_io": 0, "options": 0, "hardware": 0,
    "lie": 1, "viz": 1,
    "symmetry": 2,
    "diffusion": 3, "metrics": 3,
    "nn": 4, "data": 4,
    "config": 5,
    "models": 6,
    "evaluation": 7, "testing": 7,
    "training": 8,
    "cli": 9,
}  # fmt: skip


def _module(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module(p): p for p in SRC.rglob("*.py")}


def _imports(path: Path) -> set[str]:
    """The posediff modules a file imports (relative imports resolved; ``from X import a`` is module
    ``X.a`` when that is a module, else ``X``), at any depth of the file (function-level imports too)."""
    mod = _module(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("posediff")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.startswith("posediff"):
                for a in node.names:
                    out.add(f"{name}.{a.name}" if f"{name}.{a.name}" in MODULES else name)
    return out


def _part(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None  # None: the package's own __init__ (the lazy facade)


def _files(part: str) -> list[Path]:
    p = SRC / part
    return sorted(p.rglob("*.py")) if p.is_dir() else [p.with_suffix(".py")]


def test_every_part_has_a_level() -> None:
    parts = {_part(m) for m in MODULES} - {None}
    assert parts == set(LEVELS), (
        f"give these parts a level: {sorted(parts - set(LEVELS))}; gone: {sorted(set(LEVELS) - parts)}"
    )


def test_imports_point_down_the_layers() -> None:
    bad = []
    for module, path in MODULES.items():
        part = _part(module)
        if part is None:
            continue
        for name in sorted(_imports(path)):
            other = _part(name)
            if other is None or other == part:
                continue  # the facade (posediff.__version__) or the part itself
            if LEVELS[other] >= LEVELS[part]:
                bad.append(f"{path.relative_to(SRC)} ({part}, level {LEVELS[part]}) imports {name} "
                           f"({other}, level {LEVELS[other]})")  # fmt: skip
    assert bad == []


@pytest.mark.parametrize(
    ("part", "allowed"),
    [
        ("lie", ("posediff._registry",)),
        ("symmetry", ("posediff.lie",)),
        ("diffusion", ("posediff.lie", "posediff.symmetry", "posediff._registry")),
        ("metrics", ("posediff.symmetry", "posediff.lie", "posediff._io")),
    ],
)
def test_the_ground_floors_import_only_these(part: str, allowed: tuple[str, ...]) -> None:
    own = f"posediff.{part}"
    bad = [f"{f.relative_to(SRC)} imports {n}" for f in _files(part) for n in sorted(_imports(f))
           if not (n.startswith(own) or any(n == a or n.startswith(a + ".") for a in allowed))]  # fmt: skip
    assert bad == []


def test_the_import_graph_has_no_cycle() -> None:
    graph = {m: {n for n in _imports(p) if n in MODULES and n != m} for m, p in MODULES.items()}
    state: dict[str, int] = {}  # 1: on the path, 2: done
    cycles: list[list[str]] = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append([*path[path.index(n) :], n])
            elif n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == [], " ; ".join(" → ".join(c) for c in cycles[:5])


def test_the_facade_imports_only_the_groups_eagerly() -> None:
    """``import posediff`` loads the Lie groups; the rest of the API on first use (PEP 562)."""
    assert _imports(SRC / "__init__.py") <= {n for n in MODULES if n.startswith("posediff.lie")}


def test_evaluation_never_imports_cli_or_training() -> None:
    bad = [f"{f.relative_to(SRC)} imports {n}" for f in _files("evaluation") for n in _imports(f)
           if n.startswith(("posediff.cli", "posediff.training"))]  # fmt: skip
    assert bad == []


def test_data_never_imports_metrics_or_evaluation() -> None:
    bad = [f"{f.relative_to(SRC)} imports {n}" for f in _files("data") for n in _imports(f)
           if n.startswith(("posediff.metrics", "posediff.evaluation"))]  # fmt: skip
    assert bad == []


def test_the_old_top_level_modules_are_gone() -> None:
    gone = ["tasks", "cli", "module", "regression", "distill", "export", "checkpoint", "allowlist", "callbacks",
            "checkpoint_io", "config", "errors", "_relaunch", "predict", "evaluate", "evaluate_bop", "report"]  # fmt: skip
    assert [g for g in gone if (SRC / f"{g}.py").exists()] == []


@pytest.mark.parametrize(
    "command", sorted((SRC / "cli" / "commands").glob("[a-z]*.py")), ids=lambda p: p.stem
)
def test_commands_are_short_and_name_no_dataset(command: Path) -> None:
    """Each command reads top to bottom: no function over 80 lines; only ``data`` (the dataset commands)
    names a dataset module or data module class (a data module says what differs through
    posediff.data.PoseDataModule)."""
    tree = ast.parse(command.read_text(encoding="utf-8"))
    long = [f"{n.name}: {n.end_lineno - n.lineno + 1} lines" for n in ast.walk(tree)
            if isinstance(n, ast.FunctionDef) and n.end_lineno - n.lineno + 1 > 80]  # fmt: skip
    assert long == []
    if command.stem == "data":
        return
    assert [n for n in _imports(command) if n.startswith("posediff.data")] == []
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    assert not {n for n in names if n.startswith(("Bop", "Symsol", "SymmetryToy"))}


def test_commands_table_matches_the_modules() -> None:
    """Every command of the table names a function that exists, and every command module is used."""
    import importlib

    from posediff.cli.main import COMMANDS, DATA_COMMANDS

    used = set()
    for cmd in [*COMMANDS.values(), *DATA_COMMANDS.values()]:
        if cmd.run is None:
            continue
        module, _, function = cmd.run.partition(":")
        assert callable(getattr(importlib.import_module(f"posediff.cli.commands.{module}"), function))
        used.add(module)
    assert used == {p.stem for p in (SRC / "cli" / "commands").glob("[a-z]*.py")}


def test_importing_posediff_changes_no_environment_and_loads_no_fixture() -> None:
    """Importing posediff (its libraries imported first, which set variables of their own) leaves the
    environment as it was — the GL defaults are set by the first renderer — and the BOP fixture
    generator is loaded only when one of its names is asked for."""
    import os
    import subprocess
    import sys

    code = (
        "import os, sys\n"
        "import torch, torchvision, lightning, hydra, kornia, trimesh, cv2, matplotlib\n"
        "before = dict(os.environ)\n"
        "import posediff, posediff.data.bop, posediff.data.symsol, posediff.cli, posediff.cli.commands.fit\n"
        "import posediff.cli.commands.eval, posediff.evaluation.bop, posediff.evaluation.predict, posediff.metrics\n"
        "changed = sorted(k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k))\n"
        "print(changed, 'posediff.data.bop.fixture' in sys.modules)\n"
        "from posediff.data.bop import make_bop_fixture\n"
        "print(make_bop_fixture.__module__)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM", "LP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.splitlines() == ["[] False", "posediff.data.bop.fixture"], out.stdout + out.stderr
