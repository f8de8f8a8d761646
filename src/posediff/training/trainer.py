"""The trainer of ``posediff fit`` and ``posediff distill``, built in one place from the ``trainer``
config: its callbacks instantiated (a progress bar dropped when ``enable_progress_bar=false``, which
Lightning would refuse), the EMA callback added when asked for, and Lightning's info lines on stdout."""

from __future__ import annotations

import logging
import sys
from typing import Any

import lightning as L
from hydra.utils import instantiate
from lightning.pytorch.callbacks import ProgressBar


def lightning_logs_to_stdout() -> None:
    """Lightning's info lines ("GPU available …") once, on stdout with posediff's own output: its loggers
    also write them to stderr, where only errors belong (one line each)."""
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        log = logging.getLogger(name)
        for h in list(log.handlers):
            if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) is sys.stderr:
                log.removeHandler(h)
        log.propagate = True


def build_trainer(trainer_cfg: Any, *, ema: Any = None) -> L.Trainer:
    """``instantiate(trainer_cfg)`` with its ``callbacks`` built (and ``ema``, a callback config, added)."""
    lightning_logs_to_stdout()
    callbacks = list(instantiate(trainer_cfg.get("callbacks")) or [])
    if not trainer_cfg.get("enable_progress_bar", True):
        callbacks = [c for c in callbacks if not isinstance(c, ProgressBar)]
    if ema is not None:
        callbacks.append(instantiate(ema))
    return instantiate(trainer_cfg, callbacks=callbacks)


__all__ = ["build_trainer", "lightning_logs_to_stdout"]
