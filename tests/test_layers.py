"""The package's layers, checked from the source: which parts may import which (README "Layout")."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "posediff"


def _module(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """The posediff modules a file imports (relative imports resolved), at any depth of the file."""
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
                out.add(name)
                out |= {f"{name}.{a.name}" for a in node.names}
    return out


def _files(part: str) -> list[Path]:
    p = SRC / part
    return sorted(p.rglob("*.py")) if p.is_dir() else [p.with_suffix(".py")]


def _violations(part: str, allowed: tuple[str, ...]) -> list[str]:
    own = f"posediff.{part}"
    bad = []
    for f in _files(part):
        for name in sorted(_imports(f)):
            ok = name.startswith(own) or any(name == a or name.startswith(a + ".") for a in allowed)
            if not ok:
                bad.append(f"{f.relative_to(SRC)} imports {name}")
    return bad


@pytest.mark.parametrize(
    ("part", "allowed"),
    [
        ("lie", ("posediff._registry",)),
        ("symmetry", ("posediff.lie",)),
        ("diffusion", ("posediff.lie", "posediff.symmetry", "posediff._registry")),
        ("metrics", ("posediff.symmetry", "posediff.lie", "posediff._io")),
    ],
)
def test_lower_layers_import_only_below(part: str, allowed: tuple[str, ...]) -> None:
    assert _violations(part, allowed) == []


def test_data_never_imports_metrics() -> None:
    bad = [
        f"{f.relative_to(SRC)} imports {n}"
        for f in _files("data")
        for n in _imports(f)
        if n.startswith("posediff.metrics")
    ]
    assert bad == []


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
        "import posediff, posediff.data.bop, posediff.data.symsol, posediff.tasks, posediff.cli\n"
        "import posediff.evaluation.bop, posediff.evaluation.predict, posediff.metrics\n"
        "changed = sorted(k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k))\n"
        "print(changed, 'posediff.data.bop.fixture' in sys.modules)\n"
        "from posediff.data.bop import make_bop_fixture\n"
        "print(make_bop_fixture.__module__)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM", "LP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.splitlines() == ["[] False", "posediff.data.bop.fixture"], out.stdout + out.stderr


def test_the_composition_root_names_no_dataset() -> None:
    """``tasks.py`` instantiates and calls: no dataset module imported, no data module class named (a
    data module says what differs through posediff.data.PoseDataModule)."""
    tasks = SRC / "tasks.py"
    assert [n for n in _imports(tasks) if n.startswith("posediff.data")] == []
    names = {n.id for n in ast.walk(ast.parse(tasks.read_text(encoding="utf-8"))) if isinstance(n, ast.Name)}
    names |= {
        n.attr for n in ast.walk(ast.parse(tasks.read_text(encoding="utf-8"))) if isinstance(n, ast.Attribute)
    }
    assert not {n for n in names if n.startswith(("Bop", "Symsol", "SymmetryToy"))}


def test_data_never_imports_evaluation() -> None:
    bad = [f"{f.relative_to(SRC)} imports {n}" for f in _files("data") for n in _imports(f)
           if n.startswith(("posediff.evaluation", "posediff.evaluate", "posediff.report", "posediff.predict"))]  # fmt: skip
    assert bad == []
