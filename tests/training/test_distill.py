"""``posediff distill``: a few-step student of a toy teacher, through the real CLI, and the loss's algebra."""

import json
from pathlib import Path

import pytest
import torch

from posediff import load_checkpoint
from posediff.cli import main
from posediff.diffusion import FewStepSampler
from posediff.training.distill import SegmentDistillation, student_grid

TOY = ["+experiment=toy_se3", "trainer.max_steps=3", "trainer.val_check_interval=3",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip


@pytest.fixture(scope="module")
def teacher(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("distill") / "teacher"
    assert main(["fit", *TOY, f"hydra.run.dir={run}"]) == 0
    return run / "checkpoints" / "last.ckpt"


def test_fast_dev_run_writes_a_normal_checkpoint(teacher: Path, tmp_path: Path) -> None:
    run = tmp_path / "student"
    args = ["distill", f"ckpt_path={teacher}", "steps=3", "trainer.fast_dev_run=true",
            "trainer.enable_progress_bar=false", f"hydra.run.dir={run}"]  # fmt: skip
    assert main(args) == 0
    path = run / "checkpoints" / "last.ckpt"
    record = json.loads((run / "distill.json").read_text())
    assert record["steps"] == 3 and record["updates"] == 1 and record["student"] == str(path)
    student = load_checkpoint(path)  # the allow-listed loader of every posediff checkpoint
    assert isinstance(student.sampler, FewStepSampler) and student.sampler.num_steps == 3
    assert student.config["distill"]["teacher"] == str(teacher)
    base = load_checkpoint(teacher)
    changed = [k for k, v in student.state_dict().items() if not torch.equal(v, base.state_dict()[k])]
    assert changed and all(k.startswith("denoiser.") for k in changed), changed
    # eval / export use it unchanged: the student's own step count by default
    assert main(["eval", f"ckpt_path={path}", "num_samples=2", f"hydra.run.dir={tmp_path / 'eval'}"]) == 0
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["num_steps"] == 3 and metrics["sampler"] == "few_step"
    assert main(["export", f"ckpt_path={path}", "format=torchscript", f"out={tmp_path / 'ts'}"]) == 0
    meta = json.loads((tmp_path / "ts" / "posediff_export.json").read_text())
    assert meta["num_steps"] == 3


def test_student_loss_is_zero_on_its_own_steps(teacher: Path) -> None:
    """The target ẑ* = Log(X⁻¹X*)/(h c): trajectories made of the student's own few_step steps give
    loss 0 — ẑ_S = ẑ* lands the student's step exactly on the target, on SE(3)."""
    module = load_checkpoint(teacher).double()
    dist = SegmentDistillation(module, steps=4, num_hypotheses=6)
    cond = torch.randn(3, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    feature = dist.student.encode(cond)
    x = module.diffusion.prior((3, 6), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sampler = FewStepSampler(module.diffusion)
    states = [x]
    for a, b in zip(dist.sig_t, dist.sig_p, strict=True):
        states.append(sampler.step(dist.student.denoise_fn(), states[-1], a, b, feature, None))
    with torch.no_grad():
        loss = dist.student_loss(feature, states)
    assert float(loss) < 1e-18
    # and a perturbed target is penalised
    states[2] = module.group.rplus(states[2], 1e-2 * torch.ones(3, 6, 6, dtype=torch.float64))
    with torch.no_grad():
        assert float(dist.student_loss(feature, states)) > 1e-4


def test_grid_is_the_few_step_samplers(teacher: Path) -> None:
    module = load_checkpoint(teacher)
    sig_t, sig_p = student_grid(module.diffusion, 5)
    ref_t, ref_p = FewStepSampler(module.diffusion).sigma_grid(5)
    assert sig_t == ref_t.tolist() and sig_p == ref_p.tolist() and sig_p[-1] == 0.0


def test_training_lowers_the_loss(teacher: Path) -> None:
    """Adam on the student's loss over a fixed pool of teacher trajectories lowers that loss.

    The student starts as a copy of the teacher, close to its optimum (loss ~0.02-0.07). At lr 3e-3
    the first updates overshoot (the loss rose 2-4x by step 10) and where it stood at step 60 depended
    on how that overshoot settled: last/first 0.30-0.83 over seeds, 0.83 on an Intel CPU against a 0.8
    bound. At lr 3e-4 the loss falls smoothly: last/first after 60 updates was 0.034-0.080 over 32
    draws (4 teachers of seeds 0-3 x 8 pool seeds; 0.073 for this one), so the bound 0.3 has a 4x
    margin, while a student that is not updated stays at 1.0 (the test fails with lr=0)."""
    torch.manual_seed(0)
    module = load_checkpoint(teacher)
    lr = 3e-4
    dist = SegmentDistillation(module, steps=3, num_hypotheses=8, substeps=2, lr=lr)
    cond = torch.randn(8, 17, generator=torch.Generator().manual_seed(2))
    feature, states = dist.teacher_pool(cond, torch.Generator().manual_seed(3))
    opt = torch.optim.Adam([p for p in dist.student.denoiser.parameters()], lr=lr)
    with torch.no_grad():
        first = float(dist.student_loss(feature, states))
    for _ in range(60):
        opt.zero_grad()
        dist.student_loss(feature, states).backward()
        opt.step()
    with torch.no_grad():
        last = float(dist.student_loss(feature, states))
    assert last < 0.3 * first, (first, last, last / first)


def test_steps_zero_and_a_missing_teacher_get_one_line(
    teacher: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for args, message in (
        ([f"ckpt_path={teacher}", "steps=0"], "steps must be a whole number [1, 100], got 0"),
        ([f"ckpt_path={tmp_path / 'none.ckpt'}"], "not found"),
    ):
        capsys.readouterr()
        assert main(["distill", *args, f"hydra.run.dir={tmp_path / 'run'}"]) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(err) == 1 and err[0].startswith("posediff distill") and message in err[0], err
        assert not (tmp_path / "run" / "checkpoints").exists()
