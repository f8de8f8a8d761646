"""``posediff data make-bop``: the BOP command (config ``conf/make_bop.yaml``)."""

import sys

from omegaconf import DictConfig, OmegaConf


def make_bop(cfg: DictConfig) -> int:
    """``posediff data make-bop``: the project's small BOP-format dataset (``posediff.data.bop.fixture``)."""
    from .fixture import make_bop_fixture

    kwargs = OmegaConf.to_container(cfg, resolve=True)
    out = kwargs.pop("out")
    try:
        summary = make_bop_fixture(out, **kwargs)
    except (ValueError, RuntimeError) as e:
        print(f"posediff data make-bop: {e}", file=sys.stderr)
        return 2
    print(summary.line())
    return 0


__all__ = ["make_bop"]
