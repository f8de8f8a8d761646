"""``posediff data render`` and ``posediff data grid``: the SYMSOL commands (configs ``conf/render.yaml``,
``conf/grid.yaml``)."""

import sys

from omegaconf import DictConfig


def render_data(cfg: DictConfig) -> int:
    """``posediff data render``: render one SYMSOL / SYMSOL-T split into shards (resumable)."""
    from . import render_dataset
    from .poses import check_spec

    try:
        variant = check_spec(str(cfg.dataset), cfg.variant, str(cfg.split))
        out = cfg.out or f"data/{cfg.dataset}_{variant}_{cfg.preset.name}"
        summary = render_dataset(
            out,
            dataset=str(cfg.dataset),
            variant=variant,
            split=str(cfg.split),
            n_per_shape=int(cfg.n_per_shape),
            image_size=int(cfg.image_size),
            seed=int(cfg.seed),
            shapes=list(cfg.shapes),
            shard_size=int(cfg.shard_size),
            workers=int(cfg.workers),
            progress=bool(cfg.progress),
        )
    except (ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"posediff data render: {e}", file=sys.stderr)
        return 2
    print(summary.line())
    return 0


def render_grid(cfg: DictConfig) -> int:
    """``posediff data grid``: a picture of the five shapes (README figure)."""
    from .grid import render_grid as _grid

    try:
        path = _grid(
            cfg.out,
            dataset=str(cfg.dataset),
            variant=cfg.variant,
            per_shape=int(cfg.per_shape),
            image_size=int(cfg.image_size),
            seed=int(cfg.seed),
        )
    except ValueError as e:
        print(f"posediff data grid: {e}", file=sys.stderr)
        return 2
    print(f"figure: {path}")
    return 0


__all__ = ["render_data", "render_grid"]
