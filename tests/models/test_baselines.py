"""The regression baselines, the anchored denoiser and `posediff pretrain` through the real CLI at toy
size: each trains, `posediff eval` scores its checkpoint with the same report layout as the paper's model,
and a pretrained encoder file starts a new run. Plumbing only (learning is benchmarks/learning_speed.py)."""

import json
from pathlib import Path

import pytest
import torch

from posediff.cli import main
from posediff.models import PoseRegressionModule, load_checkpoint

SMALL = [
    "+experiment=quickstart",
    "data.mode=render",
    "data.image_size=32",
    "data.n_per_shape_train=4",
    "data.n_per_shape_test=2",
    "data.batch_size=4",
    "data.shapes=[tet,cyl]",
    "module.num_noisy=8",
    "denoiser.hidden_dim=32",
    "encoder.out_dim=32",
    "eval.num_samples=4",
    "eval.num_steps=[2]",
    "eval.before=false",
    "trainer.enable_progress_bar=false",
    "trainer.max_steps=2",
    "trainer.val_check_interval=2",
    "trainer.log_every_n_steps=1",
]
REGRESSION = ["encoder=pose", "module._target_=posediff.models.PoseRegressionModule"]
PAPER = [
    "encoder.crop_size=null",
    "encoder.depth_cue=null",
    "encoder.rotation_head=6d",
    "module.anchor=false",
    "module.aux_weight=0.0",
    "module.symmetry_fold=false",
]
MODELS = {
    "paper": PAPER,
    "quickstart": ["encoder.crop_size=32"],
    "anchored_aux_crop": [
        "encoder=pose",
        "encoder.crop_size=32",
        "module.anchor=true",
        "module.aux_weight=1.0",
    ],
    "regression": [*REGRESSION, "module.denoiser=null", "encoder.crop_size=32"],
    "iterative_regression": [
        *REGRESSION,
        "+module.iterations=2",
        "encoder.crop_size=null",
        "encoder.depth_cue=null",
        "encoder.rotation_head=6d",
    ],
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("baselines")
    out = {}
    for name, extra in MODELS.items():
        out[name] = root / name
        assert main(["fit", *SMALL, *extra, f"hydra.run.dir={out[name]}"]) == 0, name
    return out


def _header(md: str) -> list[str]:
    return [line for line in md.splitlines() if line.startswith("| shape")]


def test_every_model_trains_and_eval_reports_the_same_layout(runs: dict[str, Path], tmp_path: Path) -> None:
    headers = {}
    for name, run in runs.items():
        assert (run / "progress.log").read_text().count("step ") >= 1
        ev = tmp_path / name
        assert (
            main(
                [
                    "eval",
                    f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                    "num_samples=3",
                    f"hydra.run.dir={ev}",
                ]
            )
            == 0
        )
        m = json.loads((ev / "metrics.json").read_text())
        assert set(m["shapes"]) == {"tet", "cyl"} and m["num_samples"] == 3
        assert all(
            k in m["overall"] for k in ("spread_deg", "translation_error", "recall_rot@10", "coverage")
        )
        headers[name] = _header((ev / "metrics.md").read_text())
    assert (
        headers["regression"]
        == headers["paper"]
        == headers["anchored_aux_crop"]
        == headers["iterative_regression"]
    )


def test_regression_checkpoints_load_and_estimate_once(runs: dict[str, Path]) -> None:
    for name, iterations in (("regression", 0), ("iterative_regression", 2)):
        module = load_checkpoint(runs[name] / "checkpoints" / "last.ckpt")
        assert isinstance(module, PoseRegressionModule) and module.iterations == iterations
        m = json.loads((runs[name] / "metrics.json").read_text())
        res = m["after"]["default"]["2"]
        assert res["sampler"] == "regression" and res["num_steps"] == iterations
        x, path = module.sample(torch.rand(2, 3, 32, 32), 4, trajectory=True)
        assert x.shape == (2, 4, 4, 4) and path.shape == (iterations + 1, 2, 4, 4, 4)
        assert torch.equal(x[:, 0], x[:, 3]), "one estimate, repeated"


def test_anchored_checkpoint_keeps_its_anchor(runs: dict[str, Path]) -> None:
    module = load_checkpoint(runs["anchored_aux_crop"] / "checkpoints" / "last.ckpt")
    assert module.anchor and module.aux_weight == 1.0 and module.encoder.crop_size == 32
    x = module.sample(torch.rand(2, 3, 32, 32), 3, 2, generator=torch.Generator().manual_seed(0))
    assert x.shape == (2, 3, 4, 4) and torch.isfinite(x).all()


def test_pretrain_writes_weights_that_a_new_run_starts_from(tmp_path: Path) -> None:
    out = tmp_path / "enc.pt"
    args = [a for a in SMALL if not a.startswith("+experiment")]
    code = main(
        ["pretrain", *args, "encoder.crop_size=32", f"out={out}", f"hydra.run.dir={tmp_path / 'pre'}"]
    )
    assert code == 0 and out.is_file()
    saved = torch.load(out, weights_only=True)
    assert "encoder_state_dict" in saved and saved["posediff_pretrain"]["train"]["steps"] == 2
    run = tmp_path / "fit"
    extra = [
        "encoder=pose",
        "encoder.crop_size=32",
        "module.anchor=true",
        f"encoder.weights={out}",
        "trainer.max_steps=1",
    ]
    assert main(["fit", *SMALL, *extra, f"hydra.run.dir={run}"]) == 0
    # a missing weights file is one line
    assert (
        main(
            [
                "fit",
                *SMALL,
                "encoder=pose",
                f"encoder.weights={tmp_path / 'nope.pt'}",
                f"hydra.run.dir={run}2",
            ]
        )
        != 0
    )


def test_export_an_image_model_and_refuse_a_regression_one(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``posediff export`` of the quickstart image model (locate-then-crop ResNet, anchored denoiser):
    the exported graphs sample what ``module.sample`` samples; a regression checkpoint has no sampler
    and gets one line."""
    import torch

    from posediff.models.export import draw_from_meta, draw_inputs, load_exported

    ckpt = runs["quickstart"] / "checkpoints" / "last.ckpt"
    out = tmp_path / "ts"
    assert main(["export", f"ckpt_path={ckpt}", "format=torchscript", f"out={out}", "num_steps=2",
                 "num_samples=4"]) == 0  # fmt: skip
    module = load_checkpoint(ckpt)
    meta, run = load_exported(out, trust=True)  # a torchscript file made here
    assert meta["image_size"] == 32 and meta["group"] == module.group.name
    image = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    x0, noise = draw_inputs(module.sampler, 2, 1, 4, generator=torch.Generator().manual_seed(5))
    x1, noise1 = draw_from_meta(meta, 1, 4, generator=torch.Generator().manual_seed(5))  # the JSON alone
    assert torch.equal(x0, x1) and torch.equal(noise, noise1)
    with torch.no_grad():
        eager = module.sample(image, 4, 2, generator=torch.Generator().manual_seed(5))
        exported = run["sampler"](run["encoder"](image), x0, noise)
    torch.testing.assert_close(exported, eager, atol=1e-4, rtol=1e-4)
    capsys.readouterr()
    reg = runs["regression"] / "checkpoints" / "last.ckpt"
    assert main(["export", f"ckpt_path={reg}", "format=torchscript", f"out={tmp_path / 'reg'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no diffusion sampler" in err[0], err
    assert not (tmp_path / "reg").exists()


def test_distill_an_image_model_and_refuse_a_regression_one(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``posediff distill`` of the quickstart image model (one update): a checkpoint whose encoder is the
    teacher's, sampled by few_step at the student's steps; a regression checkpoint gets one line."""
    import torch

    ckpt = runs["quickstart"] / "checkpoints" / "last.ckpt"
    out = tmp_path / "student.ckpt"
    assert main(["distill", f"ckpt_path={ckpt}", "steps=2", "trainer.fast_dev_run=true",
                 "trainer.enable_progress_bar=false", f"out={out}", f"hydra.run.dir={tmp_path / 'run'}"]) == 0  # fmt: skip
    student, teacher = load_checkpoint(out), load_checkpoint(ckpt)
    assert student.sampler.num_steps == 2 and student.config["distill"]["steps"] == 2
    for k, v in teacher.state_dict().items():
        if k.startswith("encoder."):
            assert torch.equal(student.state_dict()[k], v), k
    image = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    poses = student.sample(image, 3, generator=torch.Generator().manual_seed(1))
    assert poses.shape == (1, 3, 4, 4) and bool(torch.isfinite(poses).all())
    capsys.readouterr()
    reg = runs["regression"] / "checkpoints" / "last.ckpt"
    assert main(["distill", f"ckpt_path={reg}", f"hydra.run.dir={tmp_path / 'reg'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a diffusion model" in err[0], err
    assert not (tmp_path / "reg" / "checkpoints").exists()


def test_flow_image_model_fits_reflows_evaluates_and_exports(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``+experiment=quickstart_flow`` (flow matching, the same image model) at toy size: fit, eval,
    ``posediff distill method=reflow`` (one update; the encoder stays the teacher's), export of the
    student; a regression checkpoint gets one line from ``method=reflow`` too."""
    flow = [a if a != "+experiment=quickstart" else "+experiment=quickstart_flow" for a in SMALL]
    run = tmp_path / "flow"
    assert main(["fit", *flow, f"hydra.run.dir={run}"]) == 0
    ckpt = run / "checkpoints" / "last.ckpt"
    teacher = load_checkpoint(ckpt)
    assert teacher.diffusion.objective == "flow" and teacher.sampler.name == "flow_euler"
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["diffusion"]["objective"] == "flow"
    out = tmp_path / "student.ckpt"
    assert main(["distill", f"ckpt_path={ckpt}", "method=reflow", "steps=2", "teacher_steps=2",
                 "trainer.fast_dev_run=true", "trainer.enable_progress_bar=false", f"out={out}",
                 f"hydra.run.dir={tmp_path / 'dist'}"]) == 0  # fmt: skip
    student = load_checkpoint(out)
    assert student.sampler.name == "flow_euler" and student.sampler.num_steps == 2
    assert student.config["distill"]["method"] == "reflow"
    for k, v in teacher.state_dict().items():
        if k.startswith("encoder."):
            assert torch.equal(student.state_dict()[k], v), k
    assert main(["eval", f"ckpt_path={out}", "num_samples=2", f"hydra.run.dir={tmp_path / 'eval'}"]) == 0
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["sampler"] == "flow_euler"
    assert main(["export", f"ckpt_path={out}", "format=torchscript", f"out={tmp_path / 'ts'}"]) == 0
    from posediff import predict

    image = torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(0))
    for model in (teacher, student):  # predict and modes() of a flow model, as of a score model
        pred = predict(model, image, num_samples=6, seed=1)
        assert pred.samples.shape == (6, 4, 4) and bool(torch.isfinite(pred.samples).all())
        assert pred.modes.poses.shape[0] >= 1 and abs(float(pred.modes.weights.sum()) - 1) < 1e-5
    capsys.readouterr()
    reg = runs["regression"] / "checkpoints" / "last.ckpt"
    assert main(["distill", f"ckpt_path={reg}", "method=reflow", f"hydra.run.dir={tmp_path / 'reg'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a diffusion model" in err[0], err
