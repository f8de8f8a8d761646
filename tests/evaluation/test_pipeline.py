"""fit → eval (multirun, report) → predict on SYMSOL-T images, through the real CLI, at toy size.

Rendering happens on the fly (``data.mode=render``, 32 px, a handful of images), so no dataset
has to exist; the model trains for two steps — these tests check the plumbing, not learning
(that is ``make demo`` and docs/image-model.md's tables).
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from posediff.cli import main
from posediff.models import CheckpointError, PoseDiffusionModule, load_checkpoint, read_checkpoint

SMALL = [
    "+experiment=quickstart",
    "group=se3",
    "data.mode=render",
    "data.image_size=32",
    "data.n_per_shape_train=4",
    "data.n_per_shape_test=2",
    "data.batch_size=4",
    "data.shapes=[tet,cube]",
    "module.num_noisy=8",
    "denoiser.hidden_dim=32",
    "encoder.out_dim=32",
    "eval.num_samples=4",
    "eval.num_steps=[2]",
    "eval.before=false",
    "trainer.enable_progress_bar=false",
]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-step quickstart run (its folder): checkpoints/last.ckpt, metrics.json, logs."""
    out = tmp_path_factory.mktemp("fit") / "run"
    code = main(
        [
            "fit",
            *SMALL,
            "trainer.max_steps=2",
            "trainer.val_check_interval=2",
            "trainer.log_every_n_steps=1",
            f"hydra.run.dir={out}",
        ]
    )
    assert code == 0
    return out


def test_fit_writes_checkpoints_logs_metrics(trained: Path) -> None:
    assert (trained / "checkpoints" / "last.ckpt").is_file()
    assert (trained / "checkpoints" / "best.ckpt").is_file(), "best.ckpt follows val/loss"
    assert (trained / "logs" / "metrics.csv").is_file()
    assert any((trained / "tb").glob("events.out.tfevents.*")), "TensorBoard logger"
    csv = (trained / "logs" / "metrics.csv").read_text()
    assert "val/loss" in csv and "lr-Adam" in csv
    metrics = json.loads((trained / "metrics.json").read_text())
    assert metrics["train"]["steps"] == 2
    row = metrics["after"]["default"]["2"]["overall"]
    for key in ("spread_deg", "translation_error", "recall_rot@5", "recall_trans@0.05", "coverage"):
        assert key in row


def test_fast_dev_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["fit", *SMALL, "trainer.fast_dev_run=true", f"hydra.run.dir={out}"]) == 0
    assert (out / "metrics.json").is_file()


def test_checkpoint_loads_without_config_files(trained: Path) -> None:
    path = trained / "checkpoints" / "last.ckpt"
    ckpt = torch.load(path, weights_only=True)  # plain tensors and containers only
    assert ckpt["posediff_config"]["module"]["cond_key"] == "image"
    module = load_checkpoint(path)
    assert isinstance(module, PoseDiffusionModule) and not module.training
    assert module.group.name == "se3"
    state = ckpt["state_dict"]
    for k, v in module.state_dict().items():
        torch.testing.assert_close(v, state[k])
    image = torch.rand(1, 3, 32, 32)
    x = module.sample(image, 3, 2)
    assert x.shape == (1, 3, 4, 4)


def test_checkpoint_refuses_other_group_or_shapes(trained: Path, tmp_path: Path) -> None:
    path = trained / "checkpoints" / "last.ckpt"
    with pytest.raises(CheckpointError, match="trained on group 'se3', not 'so3'"):
        load_checkpoint(path, group="so3")
    with pytest.raises(CheckpointError, match=r"cannot evaluate \['icosa'\]"):
        load_checkpoint(path, shapes=["tet", "icosa"])
    bogus = tmp_path / "x.ckpt"
    torch.save({"state_dict": {}}, bogus)
    with pytest.raises(CheckpointError, match="not a posediff checkpoint"):
        read_checkpoint(bogus)
    with pytest.raises(CheckpointError, match="not found"):
        read_checkpoint(tmp_path / "missing.ckpt")


def test_eval_multirun_and_report(trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sweep = tmp_path / "sweep"
    ckpt = trained / "checkpoints" / "last.ckpt"
    args = ["eval", f"ckpt_path={ckpt}", "num_samples=4", f"hydra.sweep.dir={sweep}"]
    assert main([*args, "-m", "sampler.num_steps=1,3"]) == 0
    for job, steps in (("0", 1), ("1", 3)):
        m = json.loads((sweep / job / "metrics.json").read_text())
        assert m["num_steps"] == steps and m["inputs"] == 4 and m["num_samples"] == 4
        assert set(m["shapes"]) == {"tet", "cube"}
        assert (sweep / job / "metrics.md").read_text().count("|") > 10
    report = (sweep / "report.md").read_text()
    assert "| sampler | steps | s / image | FPS |" in report
    rows = json.loads((sweep / "report.json").read_text())
    assert [r["steps"] for r in rows] == [1, 3]
    capsys.readouterr()
    assert main(["report", f"dir={sweep}"]) == 0
    assert "FPS" in capsys.readouterr().out


def test_eval_refusals(trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = trained / "checkpoints" / "last.ckpt"
    base = ["eval", f"ckpt_path={ckpt}", f"hydra.run.dir={tmp_path / 'e'}"]
    cases = [
        (["group=so3"], "trained on group 'se3', not 'so3'"),
        (["+data.shapes=[icosa]"], "cannot evaluate ['icosa']"),
        (["sampler.num_steps=0"], "sampler.num_steps must be a whole number in [1, 100]"),
        (
            ["sampler.num_steps=500"],
            "sampler.num_steps must be a whole number in [1, 100] (the schedule's levels), got 500",
        ),
        (
            ["sampler=nope"],
            "unknown sampler 'nope'; available: ancestral, crouch_grossman, few_step, flow_euler, flow_heun, heun, random_walk, rkmk",
        ),
        ([f"ckpt_path={tmp_path / 'none.ckpt'}"], "not found"),
    ]
    for extra, message in cases:
        capsys.readouterr()
        assert main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err, err
    assert not (tmp_path / "e" / "metrics.json").exists()


def test_predict_on_an_image_file(trained: Path, tmp_path: Path) -> None:
    from PIL import Image

    img = tmp_path / "in.png"
    Image.fromarray((np.random.default_rng(0).random((48, 48, 3)) * 255).astype(np.uint8)).save(img)
    out = tmp_path / "pred"
    ckpt = trained / "checkpoints" / "last.ckpt"
    code = main(
        ["predict", f"ckpt_path={ckpt}", f"image={img}", "shape=cube", "num_samples=50", "min_mode_weight=0",
         "sampler.num_steps=2", f"hydra.run.dir={out}"]
    )  # fmt: skip
    assert code == 0
    z = np.load(out / "poses.npz")
    assert z["samples"].shape == (50, 4, 4) and z["mode_weights"].sum() == pytest.approx(1.0)
    doc = json.loads((out / "poses.json").read_text())
    assert doc["num_samples"] == 50 and len(doc["modes"]) == len(z["mode_weights"])
    umask = os.umask(0)
    os.umask(umask)
    for name in ("so3.png", "translations.png", "overlay.png"):
        assert (out / name).stat().st_size > 1000, name
        assert (out / name).stat().st_mode & 0o777 == 0o666 & ~umask, "written atomically, usual permissions"
    with Image.open(out / "overlay.png") as im:
        assert im.size == (128, 128)  # 32 px model input × 4


def test_predict_test_sample_with_trajectory(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "pred"
    ckpt = trained / "checkpoints" / "last.ckpt"
    code = main(
        ["predict", f"ckpt_path={ckpt}", "index=3", "num_samples=20", "trajectory=true", "sampler.num_steps=4",
         f"hydra.run.dir={out}"]
    )  # fmt: skip
    assert code == 0
    z = np.load(out / "poses.npz")
    assert z["trajectory"].shape == (5, 20, 4, 4) and z["gt_pose"].shape == (4, 4)
    assert json.loads((out / "poses.json").read_text())["shape"] == "cube"  # index 3: 2 tet, then cube
    assert (out / "trajectory.png").stat().st_size > 1000


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["image=/no/such.png"], "image /no/such.png not found"),
        (["image={notimage}"], "is not an image"),
        ([], "give exactly one of image=PATH"),
        (["index=999"], "index=999 but the test data has 4 samples"),
        (["image={notimage}", "num_samples=0"], "num_samples must be a whole number in [1, 100000]"),
    ],
)
def test_predict_bad_input(
    trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    notimage = tmp_path / "notes.png"
    notimage.write_text("hello")
    extra = [e.format(notimage=notimage) for e in extra]
    out = tmp_path / "pred"
    ckpt = trained / "checkpoints" / "last.ckpt"
    assert main(["predict", f"ckpt_path={ckpt}", *extra, f"hydra.run.dir={out}"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err, err
    assert not list(out.glob("*.npz")) and not list(out.glob("*.png"))


def test_fit_refuses_to_resume_other_group(
    trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ckpt = trained / "checkpoints" / "last.ckpt"
    code = main(["fit", *SMALL, "group=r3so3", f"ckpt_path={ckpt}", f"hydra.run.dir={tmp_path / 'r'}"])
    assert code == 2
    assert "trained on group 'se3', not 'r3so3'" in capsys.readouterr().err


@pytest.mark.slow
def test_ddp_two_gloo_processes(tmp_path: Path) -> None:
    """``trainer=ddp`` on the CPU: Lightning starts a second rank by re-running the command (gloo)."""
    import shutil
    import subprocess
    import sys

    script = shutil.which("posediff", path=str(Path(sys.executable).parent)) or "posediff"
    out = tmp_path / "ddp"
    args = [*SMALL, "trainer=ddp", "trainer.devices=2", "trainer.accelerator=cpu", "trainer.max_steps=3"]
    res = subprocess.run(
        [script, "fit", *args, "data.n_per_shape_train=8", f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "distributed_backend=gloo" in res.stdout + res.stderr
    assert "All distributed processes registered" in res.stdout + res.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train"]["steps"] == 3
    assert (out / "checkpoints" / "last.ckpt").is_file()


@pytest.mark.slow
def test_demo_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``posediff demo`` end to end with a two-step fit (it renders the whole cpu-preset SYMSOL-T)."""
    monkeypatch.chdir(tmp_path)
    quick = ["trainer.max_steps=2", "eval.num_samples=4", "data.n_per_shape_test=1", "module.num_noisy=8"]
    assert main(["demo", "out=demo", "trainer.enable_progress_bar=false", *quick]) == 0
    out = capsys.readouterr().out
    assert "spread (°) before" in out and "t err after" in out and "demo finished in" in out
    for shape in ("tet", "cube", "cyl"):
        assert (tmp_path / "demo" / f"predict_{shape}" / "so3.png").is_file()
    assert (tmp_path / "demo" / "predict_tet" / "trajectory.png").is_file()
    assert not (tmp_path / "demo.partial").exists()


def test_resume_continues_exactly(trained: Path, tmp_path: Path) -> None:
    """``ckpt_path=last.ckpt`` restores step, optimizer and schedule: training continues at step 2."""
    out = tmp_path / "resumed"
    ckpt = trained / "checkpoints" / "last.ckpt"
    before = torch.load(ckpt, weights_only=True)
    assert before["global_step"] == 2
    args = ["fit", *SMALL, "trainer.max_steps=4", "trainer.val_check_interval=2", f"ckpt_path={ckpt}"]
    assert main([*args, f"hydra.run.dir={out}"]) == 0
    after = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert after["global_step"] == 4
    assert after["optimizer_states"][0]["state"][0]["step"] == 4, "Adam's state was restored, not restarted"
    assert json.loads((out / "metrics.json").read_text())["train"]["steps"] == 4


def test_ema_checkpoint_holds_the_averaged_weights(tmp_path: Path) -> None:
    """``ema=authors``: checkpoints (and so eval / predict) carry the EMA weights, not the live ones."""
    base = ["fit", *SMALL, "trainer.max_steps=3"]
    ema = ["ema=authors", "ema.update_every_n_steps=1", "ema.decay=0.5"]
    assert main([*base, *ema, f"hydra.run.dir={tmp_path / 'ema'}"]) == 0
    assert main([*base, f"hydra.run.dir={tmp_path / 'plain'}"]) == 0  # same seed, same batches
    with_ema = torch.load(tmp_path / "ema" / "checkpoints" / "last.ckpt", weights_only=True)
    plain = torch.load(tmp_path / "plain" / "checkpoints" / "last.ckpt", weights_only=True)
    assert int(with_ema["averaging_state"]["n_averaged"]) == 3, "one EMA update per step"
    key = "denoiser.out.weight"
    assert not torch.allclose(with_ema["state_dict"][key], plain["state_dict"][key])
    module = load_checkpoint(tmp_path / "ema" / "checkpoints" / "last.ckpt")
    torch.testing.assert_close(module.state_dict()[key], with_ema["state_dict"][key])
