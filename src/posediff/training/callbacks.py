"""Lightning callbacks posediff's trainer config uses (the rest are Lightning's own)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback, ProgressBar, RichProgressBar, TQDMProgressBar
from torch.utils.data import IterableDataset


def progress_bar(refresh_rate: int = 1) -> ProgressBar:
    """Lightning's rich progress bar on a terminal; on a pipe or CI log, its plain tqdm bar, refreshed
    every 50 steps so logs stay short."""
    if sys.stdout.isatty():
        return RichProgressBar(refresh_rate=refresh_rate)
    return TQDMProgressBar(refresh_rate=max(refresh_rate, 50))


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


class ProgressLog(Callback):
    """Plain progress lines a person can follow in any terminal, pipe or CI log, and in a file:

        step 500/2500 (20%) · loss 3.214 · anchor 31.2° · 2.1 min so far · ~8.4 min left

    every ``every_n_steps`` training steps (``loss`` is the mean since the last line; the anchor's
    held-out error when the model logs one). ``path``: also append the lines to this file (e.g. the
    run folder's ``progress.log``); ``None`` prints only. ``stdout=False`` writes the file only (for
    runs that already show a progress bar)."""

    def __init__(self, every_n_steps: int = 50, path: str | None = None, stdout: bool = True) -> None:
        self.every = max(int(every_n_steps), 1)
        self.path = Path(path) if path else None
        self.stdout = bool(stdout)
        self._start = 0.0
        self._first_step = 0
        self._losses: list[float] = []

    def _emit(self, line: str) -> None:
        if self.stdout:
            print(line, flush=True)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with self.path.open("a") as f:
                f.write(line + "\n")

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start = time.perf_counter()
        self._first_step = int(trainer.global_step)
        if trainer.is_global_zero:
            total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else "?"
            self._emit(f"training: steps {self._first_step} → {total}")

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:  # noqa: E501
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        if loss is not None:
            self._losses.append(float(loss))
        step = int(trainer.global_step)
        if not trainer.is_global_zero or step % self.every:
            return
        elapsed = time.perf_counter() - self._start
        total = int(trainer.max_steps) if trainer.max_steps and trainer.max_steps > 0 else None
        done = step - self._first_step
        parts = [f"step {step}" + (f"/{total} ({100 * step // total}%)" if total else "")]
        if self._losses:
            parts.append(f"loss {sum(self._losses) / len(self._losses):.3f}")
        anchor = trainer.callback_metrics.get("val/anchor_deg")
        if anchor is not None:
            parts.append(f"anchor {float(anchor):.1f}° (held out)")
        parts.append(f"{_minutes(elapsed)} so far")
        if total and done > 0:
            parts.append(f"~{_minutes(elapsed / done * (total - step))} left")
        self._losses = []
        self._emit(" · ".join(parts))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.is_global_zero:
            self._emit(
                f"training done: {int(trainer.global_step)} steps in {_minutes(time.perf_counter() - self._start)}"
            )


class FirstPerShape(IterableDataset):
    """The first ``per_shape`` samples of each shape of ``dataset`` (map-style or iterable; samples are
    dicts with an integer ``shape``), in the dataset's order."""

    def __init__(self, dataset: Any, per_shape: int) -> None:
        self.dataset, self.per_shape = dataset, int(per_shape)

    def __iter__(self) -> Iterator[Any]:
        counts: dict[int, int] = {}
        for sample in self.dataset:
            k = int(sample["shape"])
            if counts.get(k, 0) < self.per_shape:
                counts[k] = counts.get(k, 0) + 1
                yield sample


class TestCurve(Callback):
    """A learning curve on the test split: every ``every_n_steps`` training steps (and at step 0 and
    at the end) the model is scored on the data module's whole test split with ``num_samples``
    hypotheses per image (1: the authors' evaluation, whose expected spread does not depend on the
    count), and on the first ``coverage_per_shape`` test images of each shape with
    ``coverage_samples`` hypotheses (coverage, recall per hypothesis). Each row (step, training
    wall seconds and process CPU seconds without the evaluations, per-shape spread / translation
    error / coverage) is appended to ``path`` (JSON, written to a temporary name and renamed after
    every row), so an interrupted run keeps its curve; a resumed run (``ckpt_path=...``) continues it
    (the time totals travel in the checkpoint, the rows in the file). Global rank 0 only."""

    def __init__(
        self,
        path: str,
        every_n_steps: int = 2500,
        num_samples: int = 1,
        num_steps: int = 100,
        coverage_per_shape: int = 20,
        coverage_samples: int = 200,
        seed: int = 0,
        at_start: bool = True,
    ) -> None:
        if int(every_n_steps) < 1:
            raise ValueError(f"TestCurve every_n_steps must be ≥ 1, got {every_n_steps!r}")
        self.path = Path(path)
        self.every = int(every_n_steps)
        self.num_samples, self.num_steps = int(num_samples), int(num_steps)
        self.coverage_per_shape, self.coverage_samples = int(coverage_per_shape), int(coverage_samples)
        self.seed, self.at_start = int(seed), bool(at_start)
        self.train_seconds = 0.0  # training wall time so far, evaluations excluded (also over resumes)
        self.cpu_seconds = 0.0  # the process's CPU time in training (all its threads), alike
        self._mark: tuple[float, float] | None = None

    # -- time accounting: the clocks run in training only --
    def _tick(self) -> None:
        if self._mark is not None:
            wall, cpu = self._mark
            self.train_seconds += time.perf_counter() - wall
            self.cpu_seconds += time.process_time() - cpu
        self._mark = (time.perf_counter(), time.process_time())

    def state_dict(self) -> dict[str, Any]:
        self._tick()
        return {"train_seconds": self.train_seconds, "cpu_seconds": self.cpu_seconds}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.train_seconds = float(state_dict.get("train_seconds", 0.0))
        self.cpu_seconds = float(state_dict.get("cpu_seconds", 0.0))

    def _rows(self) -> list[dict[str, Any]]:
        if not self.path.is_file():
            return []
        import json

        return list(json.loads(self.path.read_text()).get("rows", []))

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._mark = None  # the clocks start after the first row: it is at the checkpoint's totals exactly
        if trainer.is_global_zero:
            step = int(trainer.global_step)
            kept = [r for r in self._rows() if r["step"] <= step]  # a resume drops rows beyond its checkpoint
            self._write(trainer, kept)
            if self.at_start and not any(r["step"] == step for r in kept):
                self._evaluate(trainer, pl_module)
        self._mark = (time.perf_counter(), time.process_time())

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:  # noqa: E501
        if trainer.is_global_zero and int(trainer.global_step) % self.every == 0:
            self._evaluate(trainer, pl_module)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.is_global_zero and not any(r["step"] == int(trainer.global_step) for r in self._rows()):
            self._evaluate(trainer, pl_module)

    def _evaluate(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        from ..data.resumable import eval_loader
        from ..evaluation.shapes import evaluate

        self._tick()
        start = time.perf_counter()
        dm = trainer.datamodule
        if dm is None or not hasattr(dm, "test"):
            raise ValueError("TestCurve needs a data module with a test split (trainer.fit(datamodule=...))")
        if dm.test is None:
            dm.setup("test")
        shapes = list(getattr(dm, "shapes", []))
        batch_size = int(getattr(dm, "batch_size", 16))
        full = evaluate(pl_module, eval_loader(dm.test, batch_size=batch_size), shapes,
                        num_samples=self.num_samples, num_steps=self.num_steps, seed=self.seed)  # fmt: skip
        row: dict[str, Any] = {
            "step": int(trainer.global_step),
            "train_seconds": round(self.train_seconds, 2),
            "cpu_minutes": round(self.cpu_seconds / 60.0, 3),
            "full": {"num_samples": self.num_samples, "overall": full["overall"], "shapes": full["shapes"]},
        }
        if self.coverage_per_shape > 0 and self.coverage_samples > 0:
            subset = FirstPerShape(dm.test, self.coverage_per_shape)
            sub = evaluate(pl_module, eval_loader(subset, batch_size=batch_size), shapes,
                           num_samples=self.coverage_samples, num_steps=self.num_steps, seed=self.seed)  # fmt: skip
            row["subset"] = {"num_samples": self.coverage_samples, "per_shape": self.coverage_per_shape,
                             "overall": sub["overall"], "shapes": sub["shapes"]}  # fmt: skip
        row["eval_seconds"] = round(time.perf_counter() - start, 2)
        rows = [r for r in self._rows() if r["step"] != row["step"]] + [row]
        self._write(trainer, sorted(rows, key=lambda r: r["step"]))
        spread = full["overall"].get("spread_deg", float("nan"))
        t_err = full["overall"].get("translation_error")
        t_text = f", translation {t_err:.3f}" if t_err is not None else ""
        print(f"test curve: step {row['step']} · spread {spread:.1f}°{t_text} · "
              f"{_minutes(self.train_seconds)} of training · {self.path}", flush=True)  # fmt: skip
        self._mark = (time.perf_counter(), time.process_time())  # the evaluation's time is not training's

    def _write(self, trainer: L.Trainer, rows: list[dict[str, Any]]) -> None:
        from .._io import atomic_write_json

        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(self.path, {
            "every_n_steps": self.every,
            "num_steps": self.num_steps,
            "max_steps": int(trainer.max_steps) if trainer.max_steps else None,
            "rows": rows,
        })  # fmt: skip


__all__ = ["FirstPerShape", "ProgressLog", "TestCurve", "progress_bar"]
