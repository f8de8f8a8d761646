"""The ``TestCurve`` callback (``+experiment=symsolt_cpu_long``'s learning curve): rows at step 0, every N
steps and at the end, on the whole test split and on a per-shape coverage subset; a resumed run keeps the
rows up to its checkpoint and continues the time totals."""

import json
from pathlib import Path

import pytest

from posediff.cli import main

RENDER = ["data", "render", "dataset=symsolt", "image_size=32", "shapes=[tet,cube]", "shard_size=4",
          "progress=false"]  # fmt: skip
CURVE = "posediff.training.callbacks.TestCurve"


def _fit(root: Path, run: Path, max_steps: int, *extra: str) -> int:
    return main([
        "fit", "+experiment=symsolt_cpu_long", f"data.root={root}", "data.image_size=32",
        "data.shapes=[tet,cube]", "data.batch_size=2", "module.num_noisy=4", "denoiser.hidden_dim=16",
        "encoder.out_dim=16", "encoder.crop_size=null", "encoder.depth_cue=null",
        f"trainer.max_steps={max_steps}", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
        "trainer.enable_progress_bar=false", "trainer.callbacks.0.every_n_train_steps=2",
        "trainer.callbacks.4.every_n_steps=2", "trainer.callbacks.4.num_steps=2",
        "trainer.callbacks.4.coverage_per_shape=2", "trainer.callbacks.4.coverage_samples=3",
        "eval.num_steps=[2]", f"hydra.run.dir={run}", *extra,
    ])  # fmt: skip


@pytest.fixture(scope="module")
def symsol(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("symsol")
    for split, n in (("train", 8), ("test", 3)):
        assert main([*RENDER, f"split={split}", f"n_per_shape={n}", f"out={root}"]) == 0
    return root


def test_the_long_experiment_names_the_curve_callback() -> None:
    text = (Path(__file__).resolve().parents[2] / "conf" / "experiment" / "symsolt_cpu_long.yaml").read_text()
    assert f"_target_: {CURVE}" in text  # the index 4 overrides above rely on it being the fifth


def test_rows_every_n_steps_and_a_resume_continues_them(symsol: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert _fit(symsol, run, 3) == 0
    path = run / "test_curve.json"
    rows = json.loads(path.read_text())["rows"]
    assert [r["step"] for r in rows] == [0, 2, 3]  # the start, every 2 steps, the end
    for r in rows:
        assert r["full"]["num_samples"] == 1
        assert set(r["full"]["shapes"]) == {"tet", "cube"}
        assert [int(s["inputs"]) for s in r["full"]["shapes"].values()] == [3, 3]  # the whole test split
        assert [int(s["inputs"]) for s in r["subset"]["shapes"].values()] == [2, 2]  # 2 per shape
        for part in ("full", "subset"):
            assert 0.0 <= r[part]["overall"]["spread_deg"] <= 180.0
            assert r[part]["overall"]["translation_error"] >= 0.0
        assert 0.0 <= r["subset"]["overall"]["coverage"] <= 1.0
    assert rows[0]["train_seconds"] == 0.0
    assert rows[0]["train_seconds"] < rows[1]["train_seconds"] < rows[2]["train_seconds"]
    assert rows[1]["cpu_minutes"] > 0.0

    # last.ckpt is step 2's (every 2 steps): resumed from it, the step-3 row (beyond the checkpoint) goes
    # and the rest stay
    assert _fit(symsol, run, 6, f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}") == 0
    resumed = json.loads(path.read_text())["rows"]
    assert [r["step"] for r in resumed] == [0, 2, 4, 6]
    assert resumed[:2] == rows[:2]  # kept as written
    assert resumed[2]["train_seconds"] > rows[1]["train_seconds"]  # the totals continued from the checkpoint


def test_a_bad_interval_is_refused() -> None:
    from posediff.training.callbacks import TestCurve

    with pytest.raises(ValueError, match="every_n_steps"):
        TestCurve(path="x.json", every_n_steps=0)
