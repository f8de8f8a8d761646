"""``posediff data render | grid | make-bop``: the dataset commands (configs ``conf/render.yaml``,
``conf/grid.yaml``, ``conf/make_bop.yaml``)."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from ...data.bop.fixture import make_bop_fixture
from ...data.symsol import render_dataset
from ...data.symsol.grid import render_grid
from ...data.symsol.poses import check_spec
from ..errors import user_input


def render(cfg: DictConfig) -> int:
    """``posediff data render``: render one SYMSOL / SYMSOL-T split into shards (resumable)."""
    with user_input(ValueError, FileNotFoundError, RuntimeError):
        variant = check_spec(str(cfg.dataset), cfg.variant, str(cfg.split))
        summary = render_dataset(
            cfg.out or f"data/{cfg.dataset}_{variant}_{cfg.preset.name}",
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
            look=str(cfg.look),
        )
    print(summary.line())
    return 0


def grid(cfg: DictConfig) -> int:
    """``posediff data grid``: a picture of the five shapes (the figure in docs/data.md)."""
    with user_input(ValueError):
        path = render_grid(cfg.out, dataset=str(cfg.dataset), variant=cfg.variant, per_shape=int(cfg.per_shape),
                           image_size=int(cfg.image_size), seed=int(cfg.seed))  # fmt: skip
    print(f"figure: {path}")
    return 0


def make_bop(cfg: DictConfig) -> int:
    """``posediff data make-bop``: the project's small BOP-format dataset (``posediff.data.bop.fixture``)."""
    kwargs = OmegaConf.to_container(cfg, resolve=True)
    out = kwargs.pop("out")
    with user_input(ValueError, RuntimeError):
        summary = make_bop_fixture(out, **kwargs)
    print(summary.line())
    return 0
