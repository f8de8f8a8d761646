"""Notebooks (jupytext percent .py files) run top to bottom in fast mode."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.py"))


@pytest.mark.notebooks
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path) -> None:
    env = dict(os.environ, POSEDIFF_FAST="1", MPLBACKEND="Agg", POSEDIFF_NOTEBOOK_OUT=str(tmp_path))
    res = subprocess.run(
        [sys.executable, str(path)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert any(tmp_path.iterdir()), "the notebook wrote no figure"


def test_there_are_notebooks() -> None:
    assert any(p.name.startswith("01_lie_groups") for p in NOTEBOOKS)
