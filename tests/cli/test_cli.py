"""The posediff console script: help, groups, check, and one-line errors with non-zero exits."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from posediff import cli

# the console script installed next to this interpreter (the venv need not be activated)
SCRIPT = shutil.which("posediff", path=str(Path(sys.executable).parent)) or "posediff"


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([SCRIPT, *args], capture_output=True, text=True, timeout=300)


def test_help_lists_subcommands(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert name in out


def test_console_script_help() -> None:
    res = run("--help")
    assert res.returncode == 0 and "groups" in res.stdout and "check" in res.stdout


def test_groups_lists_registry(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["groups"]) == 0
    out = capsys.readouterr().out
    for name in ("so3", "r3so3", "se3", "se2"):
        assert name in out
    assert "[ρ(3), φ(3)]" in out


def test_unknown_command_is_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["fly"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("posediff: unknown command 'fly'") and "\n" not in err


def test_unknown_group_is_one_line_error() -> None:
    res = run("check", "group=sim3")
    assert res.returncode == 2
    assert res.stderr.strip() == "posediff: unknown group 'sim3'; available: r3so3, se2, se3, so3"


def test_check_runs_contract_from_config() -> None:
    """`posediff check` builds the group with Hydra's _target_ and runs the contract."""
    res = run("check", "group=se2", "checks=[exp_matches_matrix_exp,bad_input]")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "se2: 2/2 checks passed" in res.stdout


def test_check_rejects_unknown_check() -> None:
    res = run("check", "group=so3", "checks=[nope]")
    assert res.returncode == 2 and "unknown check" in res.stderr


def test_module_entrypoint() -> None:
    res = subprocess.run([sys.executable, "-m", "posediff.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "commands:" in res.stdout


def test_two_runs_started_in_the_same_second_get_their_own_folders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two ``fit``s in one second shared ``outputs/fit/<stamp>`` (``.hydra``, ``metrics.json`` and
    ``progress.log`` mixed, ``last.ckpt`` beside ``last-v1.ckpt``); the clock is frozen here, so the
    folders differ only by the command's own token (``${posediff.run_id:}``)."""
    from datetime import datetime

    import hydra.core.utils
    from omegaconf import OmegaConf

    class Frozen(datetime):
        @classmethod
        def now(cls, tz=None):  # noqa: ANN001, ANN206 - datetime.now's
            return cls(2026, 1, 1, 0, 0, 0)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(hydra.core.utils, "datetime", Frozen)  # Hydra's ${now:} reads this
    toy = ["+experiment=toy_so3", "trainer.max_steps=1", "trainer.enable_progress_bar=false", "data.num_train=16",
           "data.batch_size=8", "data.num_test_per_shape=1", "module.num_noisy=2", "denoiser.hidden_dim=16",
           "eval.before=false", "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip
    for seed in (0, 1):
        assert cli.main(["fit", *toy, f"seed={seed}"]) == 0
    runs = sorted((tmp_path / "outputs" / "fit").iterdir())
    assert len(runs) == 2 and all(r.name.startswith("2026-01-01_00-00-00_") for r in runs), runs
    seeds = sorted(OmegaConf.load(r / ".hydra" / "config.yaml").seed for r in runs)
    assert seeds == [0, 1]
    for r in runs:  # each its own checkpoint, no last-v1.ckpt
        assert sorted(p.name for p in (r / "checkpoints").iterdir()) == ["last.ckpt"], r
