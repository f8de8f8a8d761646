"""The pose-model contract over every image model posediff configures: the paper's diffusion model, the
anchored denoiser (diffusion loss only / with the auxiliary loss / locate-then-crop), on SE(3),
R³×SO(3) and SO(3), and the regression baselines — each built from the configs as `posediff fit` does."""

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from posediff.cli import config_dir
from posediff.config import register_resolvers
from posediff.testing import POSE_MODEL_CHECKS, synthetic_batch

TINY = [
    "data.image_size=32",
    "encoder.out_dim=16",
    "denoiser.hidden_dim=32",
    "denoiser.num_frequencies=8",
    "denoiser.time_dim=16",
    "module.num_noisy=4",
]
ANCHOR = ["encoder=pose", "module.anchor=true"]
REGRESSION = [
    "encoder=pose",
    "module._target_=posediff.models.PoseRegressionModule",
    "module.denoiser=null",
]
ITERATIVE = [
    "encoder=pose",
    "module._target_=posediff.models.PoseRegressionModule",
    "+module.iterations=2",
]

VARIANTS = {
    "paper": [],
    "paper_pose_encoder": ["encoder=pose"],
    "anchored": ANCHOR,
    "anchored_aux": [*ANCHOR, "module.aux_weight=1.0"],
    "anchored_aux_crop": [*ANCHOR, "module.aux_weight=1.0", "encoder.crop_size=32"],
    "anchored_r3so3": [*ANCHOR, "group=r3so3"],
    "anchored_so3": [*ANCHOR, "group=so3", "encoder.crop_size=null", "encoder.depth_cue=null"],
    "regression": REGRESSION,
    "regression_crop": [*REGRESSION, "encoder.crop_size=32"],
    "iterative_regression": ITERATIVE,
    "anchored_aux_invariant_crop": [
        *ANCHOR,
        "module.aux_weight=1.0",
        "encoder.crop_size=32",
        "encoder.rotation_head=invariant",
    ],
    "regression_invariant": [*REGRESSION, "encoder.rotation_head=invariant"],
    "iterative_regression_invariant": [*ITERATIVE, "encoder.rotation_head=invariant"],
    "paper_invariant_probe": ["encoder=pose", "encoder.rotation_head=invariant"],
}

_CACHE: dict[str, object] = {}
pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")


def build(name: str):  # noqa: ANN201
    if name not in _CACHE:
        register_resolvers()
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("fit", overrides=["+experiment=quickstart", *TINY, *VARIANTS[name]])
        torch.manual_seed(0)
        _CACHE[name] = instantiate(cfg.module)
    return _CACHE[name]


@pytest.mark.parametrize("check", list(POSE_MODEL_CHECKS))
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_pose_model_contract(variant: str, check: str) -> None:
    module = build(variant)
    group = module.group.name
    POSE_MODEL_CHECKS[check](module, synthetic_batch(4, 32, group))
