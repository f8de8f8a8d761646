"""Lightning callbacks posediff's trainer config uses (the rest are Lightning's own)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback, ProgressBar, RichProgressBar, TQDMProgressBar


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


__all__ = ["ProgressLog", "progress_bar"]
