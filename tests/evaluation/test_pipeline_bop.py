"""make-bop → fit → eval (multirun) on the project's BOP fixture, through the real CLI.

The model trains for one or two steps: these tests check the plumbing (the paper's experiment
config runs, the checkpoint carries the translation statistics, eval writes the Table 3 layout
and the BOP19 CSV), not learning.
"""

import json
from pathlib import Path

import pytest

from posediff.cli import main
from posediff.metrics.bop19 import read_bop19_csv
from posediff.models import read_checkpoint

SMALL = [
    "+experiment=tless_se3",
    "encoder.arch=resnet18",
    "encoder.out_dim=32",
    "denoiser.hidden_dim=32",
    "data.image_size=32",
    "data.batch_size=4",
    "data.num_workers=0",
    "module.num_noisy=8",
    "trainer.precision=32-true",
    "trainer.enable_progress_bar=false",
    "eval.num_steps=[2]",
]


def test_make_bop_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fx"
    args = ["data", "make-bop", f"out={out}", "width=160", "height=120", "pbr_images=2", "train_views=2",
            "test_images=1", "progress=false"]  # fmt: skip
    assert main(args) == 0
    assert "BOP fixture in" in capsys.readouterr().out
    assert (out / "test_targets_bop19.json").is_file() and (out / "models" / "models_info.json").is_file()
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "already exists" in err and len(err.splitlines()) == 1


def test_paper_experiment_fast_dev_run(bop_root: Path, tmp_path: Path) -> None:
    """The issue's CI command: the paper's settings (ResNet34, 224 px, bf16) for one batch on the CPU."""
    out = tmp_path / "run"
    code = main(["fit", "+experiment=tless_se3", f"data.root={bop_root}", "trainer.fast_dev_run=true",
                 "data.num_workers=0", "data.batch_size=4", "module.num_noisy=16", f"hydra.run.dir={out}"])  # fmt: skip
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    res = metrics["after"]["default"]["100"]
    assert res["kind"] == "bop" and res["targets"] > 0
    for key in ("AR_MSPD", "AR_MSSD", "AR_VSD", "AR", "recall_rot@2", "recall_trans@10cm", "recall_z@5cm"):
        assert 0.0 <= res["overall"][key] <= 1.0
    assert read_bop19_csv(res["bop19_csv"])
    assert "| object | MSPD | MSSD | VSD | AR |" in (out / "metrics.md").read_text()


@pytest.fixture(scope="module")
def trained(bop_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bopfit") / "run"
    code = main(["fit", *SMALL, f"data.root={bop_root}", "trainer.max_steps=2", "trainer.val_check_interval=2",
                 f"hydra.run.dir={out}"])  # fmt: skip
    assert code == 0
    return out


def test_checkpoint_carries_translation_statistics(trained: Path) -> None:
    cfg = read_checkpoint(trained / "checkpoints" / "last.ckpt")["posediff_config"]
    stats = cfg["data"]["translation_stats"]
    assert len(stats["mean"]) == 3 and min(stats["std"]) > 0


def test_eval_writes_table3_and_csv(
    trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ckpt = trained / "checkpoints" / "last.ckpt"
    out = tmp_path / "eval"
    assert main(["eval", f"ckpt_path={ckpt}", "sampler.num_steps=2", f"hydra.run.dir={out}"]) == 0
    printed = capsys.readouterr().out
    assert "BOP19 estimates:" in printed and "x@2cm" in printed
    csvs = list(out.glob("posediff_*-test.csv"))
    assert len(csvs) == 1
    rows = read_bop19_csv(csvs[0])
    result = json.loads((out / "metrics.json").read_text())
    assert len(rows) == result["targets"] - result["skipped"]
    assert result["data"]["translation_stats"]  # decoded with the training split's statistics
    # a step sweep collects into one table with the BOP columns
    sweep = tmp_path / "sweep"
    assert main(["eval", f"ckpt_path={ckpt}", "max_inputs=4", "vsd=false", "-m", "sampler.num_steps=1,2",
                 f"hydra.sweep.dir={sweep}"]) == 0  # fmt: skip
    report = (sweep / "report.md").read_text()
    assert "| MSPD | MSSD | VSD | AR |" in report and report.count("random_walk") == 2


def test_eval_refuses_missing_data(trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = trained / "checkpoints" / "last.ckpt"
    code = main(
        ["eval", f"ckpt_path={ckpt}", f"+data.root={tmp_path / 'nothere'}", f"hydra.run.dir={tmp_path}"]
    )
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing BOP models folder" in err and "make-bop" in err


def test_predict_on_a_test_target(trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    ckpt = trained / "checkpoints" / "last.ckpt"
    out = tmp_path / "pred"
    code = main(["predict", f"ckpt_path={ckpt}", "index=1", "num_samples=64", "trajectory=true",
                 "sampler.num_steps=3", f"hydra.run.dir={out}"])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "in scene" in printed and "mm" in printed
    for name in ("poses.npz", "poses.json", "so3.png", "translations.png", "trajectory.png"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "poses.json").read_text())
    assert doc["frame"].startswith("camera") and doc["obj_id"] in (1, 2, 3)
    arrays = np.load(out / "poses.npz")
    samples, gt = arrays["samples"], arrays["gt_pose"]
    assert samples.shape == (64, 4, 4) and gt.shape == (4, 4)
    assert np.allclose(samples[:, :3, :3] @ samples[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-6)
    assert 100 < np.median(samples[:, 2, 3]) < 5000  # decoded to millimetres in front of the camera
    # an image alone is not enough for a BOP model; an index past the targets is one line too
    from PIL import Image

    Image.new("RGB", (32, 32)).save(tmp_path / "x.png")  # a valid image (checked before the model)
    assert (
        main(["predict", f"ckpt_path={ckpt}", f"image={tmp_path / 'x.png'}", f"hydra.run.dir={tmp_path}"])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "give index=N" in err
    assert main(["predict", f"ckpt_path={ckpt}", "index=100000", f"hydra.run.dir={tmp_path}"]) == 2
    assert "index=100000 but the test split has" in capsys.readouterr().err
