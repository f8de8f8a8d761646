"""Lightning callbacks posediff's trainer config uses (the rest are Lightning's own)."""

from __future__ import annotations

import sys

from lightning.pytorch.callbacks import ProgressBar, RichProgressBar, TQDMProgressBar


def progress_bar(refresh_rate: int = 1) -> ProgressBar:
    """Lightning's rich progress bar on a terminal; on a pipe or CI log, its plain tqdm bar, refreshed
    every 50 steps so logs stay short."""
    if sys.stdout.isatty():
        return RichProgressBar(refresh_rate=refresh_rate)
    return TQDMProgressBar(refresh_rate=max(refresh_rate, 50))


__all__ = ["progress_bar"]
