"""``posediff distill ckpt_path=TEACHER steps=5 [method=segment|reflow]``: a few-step student
(:mod:`posediff.training.distill`: segment distillation of a score model, rectification of a flow model)
trained on the teacher's own training data, written as a normal checkpoint (``out``, default
``<run>/checkpoints/last.ckpt``) plus ``distill.json`` in the run folder."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ..._io import atomic_write_json
from ...models import CONFIG_KEY, PoseDiffusionModule, module_from_checkpoint, read_checkpoint
from ...options import whole
from ...training.distill import METHODS, DistillationError, Reflow, SegmentDistillation, save_student
from ...training.trainer import build_trainer
from ..errors import user_input
from ..runs import mean


def run(cfg: DictConfig) -> int:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    with user_input(ValueError, FileNotFoundError, RuntimeError):
        teacher, run_cfg, steps, out, datamodule = setup(cfg, out_dir)
    print(datamodule.describe())
    start = time.perf_counter()
    losses: list[float] = []
    updates = 0
    for _ in range(int(cfg.rounds) if cfg.method == "reflow" else 1):  # each round's student teaches the next
        distiller = make_distiller(cfg, teacher, steps)
        trainer = build_trainer(cfg.trainer)
        trainer.fit(distiller, datamodule=datamodule)
        losses += distiller.loss_history
        updates += int(trainer.global_step)
        teacher = distiller.student.eval()
    seconds = time.perf_counter() - start
    record = {
        "teacher": str(cfg.ckpt_path),
        "method": str(cfg.method),
        "steps": steps,
        **({"substeps": int(cfg.substeps)} if cfg.method == "segment" else
           {"teacher_steps": int(cfg.teacher_steps), "rounds": int(cfg.rounds)}),
        "num_hypotheses": int(cfg.num_hypotheses),
        "reuse": int(cfg.reuse),
        "updates": updates,
        "lr": float(cfg.lr),
        "lr_final": float(cfg.lr_final),
        "seconds": seconds,
        "loss_first": mean(losses[:50]),
        "loss_last": mean(losses[-50:]),
    }  # fmt: skip
    student = distiller.student.cpu().eval()
    config = distiller.student_config(OmegaConf.to_container(run_cfg, resolve=True), record)
    path = save_student(student, config, out)
    atomic_write_json(out_dir / "distill.json", {**record, "student": str(path)})
    print(
        f"distilled {record['updates']} updates in {seconds:.0f} s; loss {record['loss_first']:.4f} → "
        f"{record['loss_last']:.4f}"
    )
    sampler = "flow_euler" if cfg.method == "reflow" else "few_step"
    print(f"student: {path} (sampler {sampler}, num_steps={steps})")
    print(f"next:    posediff eval ckpt_path={path}")
    return 0


def make_distiller(cfg: DictConfig, teacher: PoseDiffusionModule, steps: int) -> SegmentDistillation:
    """The student's trainer for ``cfg.method``, with what it will do printed."""
    common = {"num_hypotheses": int(cfg.num_hypotheses), "reuse": int(cfg.reuse), "lr": float(cfg.lr),
              "lr_final": float(cfg.lr_final)}  # fmt: skip
    if cfg.method == "reflow":
        print(f"student: {steps} flow_euler steps, re-fitted on the teacher's pairs "
              f"({cfg.teacher_steps} flow_heun steps each)")  # fmt: skip
        return Reflow(teacher, steps=steps, teacher_steps=int(cfg.teacher_steps), **common)
    distiller = SegmentDistillation(teacher, steps=steps, substeps=int(cfg.substeps), **common)
    print(
        f"student: {steps} few_step steps (σ {', '.join(f'{s:.3g}' for s in distiller.sig_t)} → 0); "
        f"teacher: {cfg.substeps} Heun steps per student step"
    )
    return distiller


def setup(cfg: DictConfig, out_dir: Path) -> tuple[PoseDiffusionModule, DictConfig, int, Path, Any]:
    """The options checked, then the teacher, its run config (with ``data`` overrides), the student's
    step count and file, and the teacher's training data, set up."""
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    ckpt = read_checkpoint(cfg.ckpt_path)
    teacher = module_from_checkpoint(ckpt, cfg.ckpt_path)
    if not isinstance(teacher, PoseDiffusionModule) or not hasattr(teacher.sampler, "step"):
        raise DistillationError(
            f"checkpoint {cfg.ckpt_path} is a {type(teacher).__name__}, not a diffusion model: "
            "posediff distill needs a score or flow model trained by posediff fit"
        )
    if cfg.method not in METHODS:
        raise DistillationError(f"unknown method {cfg.method!r}; options: {', '.join(METHODS)}")
    objective = teacher.diffusion.objective
    if METHODS[str(cfg.method)] != objective:
        fits = next(m for m, o in METHODS.items() if o == objective)
        kind = "a flow model (diffusion.objective=flow)" if objective == "flow" else "a score model"
        raise DistillationError(f"method={cfg.method} cannot distill {kind}; use method={fits}")
    steps = whole(cfg.steps, "steps", 1, teacher.diffusion.schedule.num_levels)
    for key in ("substeps", "teacher_steps", "rounds", "num_hypotheses", "reuse", "max_steps"):
        whole(cfg[key], key)
    if not (float(cfg.lr) > 0 and float(cfg.lr_final) > 0):
        raise DistillationError(f"lr and lr_final must be > 0, got {cfg.lr} and {cfg.lr_final}")
    run_cfg = OmegaConf.create(ckpt[CONFIG_KEY])
    if cfg.get("data"):
        run_cfg.data = OmegaConf.merge(run_cfg.data, OmegaConf.to_container(cfg.data, resolve=False))
    out = Path(str(cfg.out)) if cfg.out else out_dir / "checkpoints" / "last.ckpt"
    if out.is_dir():
        raise DistillationError(f"out={out} is a folder; give the student checkpoint's file name")
    datamodule = instantiate(run_cfg.data)
    datamodule.setup("fit")
    return teacher, run_cfg, steps, out, datamodule
