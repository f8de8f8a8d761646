"""``posediff fit diffusion.objective=flow`` and ``posediff distill method=reflow`` on the toys, through the
real CLI, and the rectification's algebra: the pairs are the teacher's ODE, the loss the flow objective
on them, and the student a normal checkpoint that eval, predict's sampler and export use unchanged."""

import json
from pathlib import Path

import pytest
import torch
from torch.testing import assert_close

from posediff import load_checkpoint
from posediff.cli import main
from posediff.diffusion import FlowEulerSampler, FlowHeunSampler
from posediff.models.export import SamplingLoop, draw_inputs
from posediff.training.distill import Reflow

TOY = ["+experiment=toy_se3_flow", "trainer.max_steps=3", "trainer.val_check_interval=3",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]"]  # fmt: skip


@pytest.fixture(scope="module")
def teacher(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("reflow") / "teacher"
    assert main(["fit", *TOY, f"hydra.run.dir={run}"]) == 0
    return run


def test_flow_fit_writes_a_flow_checkpoint_evaluated_by_both_flow_samplers(teacher: Path) -> None:
    module = load_checkpoint(teacher / "checkpoints" / "last.ckpt")
    assert module.diffusion.objective == "flow" and isinstance(module.sampler, FlowEulerSampler)
    metrics = json.loads((teacher / "metrics.json").read_text())
    assert metrics["diffusion"]["objective"] == "flow"
    text = (teacher / "metrics.md").read_text()
    assert "flow_euler" in text and "flow_heun" in text


def test_reflow_writes_a_normal_checkpoint(teacher: Path, tmp_path: Path) -> None:
    ckpt = teacher / "checkpoints" / "last.ckpt"
    run = tmp_path / "student"
    assert main(["distill", f"ckpt_path={ckpt}", "method=reflow", "steps=3", "teacher_steps=3", "rounds=2",
                 "trainer.fast_dev_run=true", "trainer.enable_progress_bar=false", f"hydra.run.dir={run}"]) == 0  # fmt: skip
    record = json.loads((run / "distill.json").read_text())
    assert record["method"] == "reflow" and record["rounds"] == 2 and record["updates"] == 2
    student = load_checkpoint(run / "checkpoints" / "last.ckpt")
    assert isinstance(student.sampler, FlowEulerSampler) and student.sampler.num_steps == 3
    base = load_checkpoint(ckpt)
    changed = [k for k, v in student.state_dict().items() if not torch.equal(v, base.state_dict()[k])]
    assert changed and all(k.startswith("denoiser.") for k in changed), changed
    assert main(["eval", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "num_samples=2",
                 f"hydra.run.dir={tmp_path / 'eval'}"]) == 0  # fmt: skip
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["num_steps"] == 3 and metrics["sampler"] == "flow_euler"


def test_exported_loop_is_the_samplers(teacher: Path) -> None:
    """The export's sampling loop (the sampler's own steps on its time grid, the prior as an input)
    gives the poses ``module.sample`` gives with the same generator."""
    module = load_checkpoint(teacher / "checkpoints" / "last.ckpt").double().eval()
    cond = torch.randn(2, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    for sampler in (FlowEulerSampler(module.diffusion), FlowHeunSampler(module.diffusion)):
        x_init, noise = draw_inputs(
            sampler, 4, 2, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64
        )
        with torch.no_grad():
            out = SamplingLoop(module, sampler, 4)(module.encode(cond), x_init, noise)
        ref = module.sample(cond, 5, 4, sampler=sampler, generator=torch.Generator().manual_seed(1))
        assert_close(out, ref)


def test_export_refuses_a_renoising_flow_sampler(teacher: Path, tmp_path: Path) -> None:
    """``fresh_prior=true`` draws a prior pose per step, not a tangent noise the exported loop takes: one
    ExportError naming the fix, and nothing written."""
    from posediff.models.export import ExportError, export_module

    module = load_checkpoint(teacher / "checkpoints" / "last.ckpt").eval()
    module.sampler = FlowEulerSampler(module.diffusion, fresh_prior=True)
    with pytest.raises(ExportError, match="sampler.fresh_prior=false"):
        export_module(module, tmp_path / "ts", "torchscript", example=torch.randn(1, 17))
    assert not (tmp_path / "ts").exists()


def test_pairs_are_the_teachers_ode_and_the_loss_its_flow_objective(teacher: Path) -> None:
    """teacher_pool's X₁ is where flow_heun carries X₀; a student whose velocity is exactly
    Log(X₀⁻¹X₁) along each pair's geodesic would have loss 0, and Adam on a fixed pool lowers the loss."""
    module = load_checkpoint(teacher / "checkpoints" / "last.ckpt").double()
    reflow = Reflow(module, steps=2, teacher_steps=3, num_hypotheses=6, lr=3e-4)
    cond = torch.randn(4, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    feature, (x0, x1) = reflow.teacher_pool(cond, torch.Generator().manual_seed(3))
    heun = FlowHeunSampler(module.diffusion)
    x = x0
    for a, b in zip(*[v.tolist() for v in heun.sigma_grid(3)], strict=True):
        x = heun.step(module.denoise_fn(), x, a, b, feature, None)
    assert_close(x1, x)
    batch = module.diffusion.interpolate(x1, x0=x0)
    assert_close(batch.target, module.group.rminus(x0, x1))
    assert float(module.diffusion.loss(batch.target, batch)) == 0.0
    opt = torch.optim.Adam(list(reflow.student.denoiser.parameters()), lr=3e-4)
    torch.manual_seed(0)
    with torch.no_grad():
        first = float(reflow.student_loss(feature, [x0, x1]))
    for _ in range(60):
        opt.zero_grad()
        reflow.student_loss(feature, [x0, x1]).backward()
        opt.step()
    with torch.no_grad():
        last = float(reflow.student_loss(feature, [x0, x1]))
    assert last < 0.7 * first, (first, last)


def test_reflow_of_a_score_model_and_an_unknown_method_get_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dsm = ["+experiment=toy_so3", *TOY[1:], "eval.samplers=null"]
    assert main(["fit", *dsm, f"hydra.run.dir={tmp_path / 'dsm'}"]) == 0
    ckpt = tmp_path / "dsm" / "checkpoints" / "last.ckpt"
    for args, message in ((["method=reflow"], "use method=segment"),
                          (["method=magic"], "unknown method 'magic'; options: segment, reflow")):  # fmt: skip
        _refused_in_one_line(ckpt, args, message, tmp_path, capsys)


def _refused_in_one_line(
    ckpt: Path, args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``posediff distill`` refuses: exit 2, one stderr line with ``message``, no checkpoint written."""
    capsys.readouterr()
    assert main(["distill", f"ckpt_path={ckpt}", *args, f"hydra.run.dir={tmp_path / 'run'}"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("posediff distill") and message in err[0], err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_segment_distillation_of_a_flow_model_gets_one_line(
    teacher: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ckpt = teacher / "checkpoints" / "last.ckpt"
    message = "method=segment cannot distill a flow model (diffusion.objective=flow); use method=reflow"
    _refused_in_one_line(ckpt, ["method=segment"], message, tmp_path, capsys)
