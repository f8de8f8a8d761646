"""``module.locate_weight``: the weight of a locate-then-crop encoder's translation regression in the
training loss (``PoseModule.side_losses``); 0 leaves the locator untrained."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from torch.testing import assert_close

from posediff.config import register_resolvers
from posediff.nn.pose_encoder import Encoding

CONF = Path(__file__).resolve().parents[2] / "conf"


def _module(weight: float):  # noqa: ANN202 - PoseDiffusionModule
    register_resolvers()
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(
            "fit",
            overrides=["+experiment=toy_se3", "denoiser.hidden_dim=16", f"module.locate_weight={weight}"],
        )
    m = instantiate(cfg.module)
    m.log = lambda *a, **k: None
    return m


@pytest.mark.parametrize("weight", [0.0, 1.0, 2.5])
def test_locate_weight_scales_the_locators_regression(weight: float) -> None:
    m = _module(weight)
    assert m.locate_weight == weight
    g = torch.Generator().manual_seed(0)
    pose = m.group.sample_uniform((5,), generator=g)
    located = torch.randn(5, 3, generator=g, dtype=pose.dtype).requires_grad_(True)
    enc = Encoding(torch.zeros(5, 4, dtype=pose.dtype), rotation=None, located=located)
    total = m.side_losses({"pose": pose}, enc, "train")
    expected = weight * (located - pose[:, :3, 3]).square().sum(-1).mean()
    assert_close(total, expected)
    (grad,) = torch.autograd.grad(total, located, allow_unused=True)
    if weight == 0:
        assert grad is None or torch.count_nonzero(grad) == 0  # the locator gets no gradient
    else:
        assert_close(grad, weight * 2 * (located - pose[:, :3, 3]).detach() / 5)


@pytest.mark.parametrize("bad", ["abc", -1.0])
def test_locate_weight_is_checked_before_anything_is_built(bad: object) -> None:
    """``posediff fit module.locate_weight=...`` is refused in one line naming the key (posediff.options)."""
    from posediff.options import OptionError, check_options

    with pytest.raises(OptionError, match="locate_weight"):
        check_options({"module": {"locate_weight": bad}})
