"""Every config composes and builds: each experiment, and each option of every config group."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from posediff.config import register_resolvers
from posediff.diffusion import Diffusion, NoiseKernel, NoiseSchedule, Sampler
from posediff.models import PoseDiffusionModule, PoseModule
from posediff.nn import pose_input_dim

CONF = Path(__file__).resolve().parents[2] / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
# trainer paths use ${hydra:runtime.output_dir}; outside a Hydra run, point them at a folder
NO_HYDRA = ["trainer.default_root_dir=.", "trainer.logger=null", "trainer.callbacks=null"]


def _compose(overrides: list[str]):  # noqa: ANN202
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="fit", overrides=overrides)


# image experiments read rendered shards; here they render one image per shape on the fly instead
RENDER_SMALL = [
    "data.mode=render",
    "data.n_per_shape_train=1",
    "data.n_per_shape_test=1",
    "data.num_workers=0",
    "data.batch_size=2",
]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_builds(experiment: str, request: pytest.FixtureRequest) -> None:
    probe = _compose([f"+experiment={experiment}", *NO_HYDRA])
    images = probe.module.cond_key == "image"
    small = RENDER_SMALL if images else []
    if str(probe.data._target_).startswith("posediff.data.bop"):  # BOP experiments read the fixture
        small = [
            f"data.root={request.getfixturevalue('bop_root')}",
            "data.num_workers=0",
            "data.batch_size=2",
        ]
    cfg = _compose([f"+experiment={experiment}", *NO_HYDRA, *small])
    module = instantiate(cfg.module)
    assert isinstance(module, PoseModule)  # a diffusion model, or a regression baseline (its sibling)
    data = instantiate(cfg.data)
    data.setup("fit")
    batch = next(iter(data.train_dataloader()))
    cond = batch[module.cond_key][:2]
    if images:
        assert cond.shape[-3:] == (3, cfg.data.image_size, cfg.data.image_size)
        assert cfg.encoder.image_size == cfg.data.image_size
    if isinstance(module, PoseDiffusionModule):
        feature = module.unpack(module.encode(cond))[0]  # the anchored denoiser packs its anchor behind
        assert feature.shape == (2, cfg.denoiser.cond_dim), "denoiser.cond_dim must match the condition"
    x = module.sample(cond, 3, 2)
    assert x.shape == (2, 3, module.group.matrix_dim, module.group.matrix_dim)
    loss = module.training_step({k: v[:2] for k, v in batch.items()}, 0)
    assert torch.isfinite(loss)
    trainer = instantiate(cfg.trainer)  # the Lightning Trainer of the experiment builds too
    assert trainer.max_steps == cfg.trainer.max_steps


def test_paper_experiments_settings() -> None:
    """symsol_so3 / symsolt_se3 / symsolt_r3so3 keep the paper's settings (supplement; reference code)."""
    for name, group, steps in (
        ("symsol_so3", "so3", 400_000),
        ("symsolt_se3", "se3", 800_000),
        ("symsolt_r3so3", "r3so3", 800_000),
    ):
        cfg = _compose([f"+experiment={name}", *NO_HYDRA])
        assert cfg.group._target_.lower().endswith(group)
        assert (cfg.encoder.arch, cfg.data.image_size, cfg.data.batch_size, cfg.module.num_noisy) == (
            "resnet34",
            224,
            16,
            256,
        )
        assert (cfg.module.lr, cfg.module.lr_final, cfg.module.decay_start) == (1e-4, 1e-5, 0.5)
        assert cfg.trainer.max_steps == steps and cfg.schedule.num_levels == 100


def test_tless_experiments_settings() -> None:
    """tless_se3 / tless_r3so3: ResNet34 at 224 px, 32 images × 256 noisy poses, 400k steps, PBR + real."""
    for name, group in (("tless_se3", "se3"), ("tless_r3so3", "r3so3")):
        cfg = _compose([f"+experiment={name}", *NO_HYDRA])
        assert cfg.group._target_.lower().endswith(group)
        assert (cfg.encoder.arch, cfg.data.image_size, cfg.data.batch_size, cfg.module.num_noisy) == (
            "resnet34",
            224,
            32,
            256,
        )
        assert list(cfg.data.train_splits) == ["train_pbr", "train_primesense"]
        assert (cfg.data.test_split, cfg.data.targets) == ("test_primesense", "test_targets_bop19.json")
        assert (cfg.data.dzi_shift, cfg.data.dzi_scale, cfg.data.dzi_pad) == (0.25, 0.25, 1.5)
        assert cfg.data.rotation == "allocentric" and cfg.data.augment is not None
        assert (cfg.module.lr, cfg.module.lr_final, cfg.module.decay_start) == (1e-4, 1e-5, 0.5)
        assert cfg.trainer.max_steps == 400_000 and cfg.schedule.num_levels == 100
        assert cfg.eval.num_samples == 1


def test_ema_and_ddp_options() -> None:
    cfg = _compose(["+experiment=quickstart", "ema=authors", "trainer=ddp", *NO_HYDRA])
    ema = instantiate(cfg.ema)
    assert type(ema).__name__ == "EMAWeightAveraging"
    assert cfg.trainer.strategy == "ddp" and cfg.trainer.max_steps == 2500


@pytest.mark.parametrize(
    ("group_name", "option"),
    [("kernel", p.stem) for p in (CONF / "kernel").glob("*.yaml")]
    + [("schedule", p.stem) for p in (CONF / "schedule").glob("*.yaml")]
    + [("sampler", p.stem) for p in (CONF / "sampler").glob("*.yaml")],
)
def test_every_option_builds(group_name: str, option: str) -> None:
    overrides = ["+experiment=toy_se3", f"{group_name}={option}"]
    if group_name == "sampler" and Sampler.registry[option].objective == "flow":
        overrides.append("diffusion.objective=flow")  # a flow sampler refuses a score model
    cfg = _compose([*overrides, *NO_HYDRA])
    diffusion = instantiate(cfg.diffusion)
    assert isinstance(diffusion, Diffusion)
    assert isinstance(diffusion.kernel, NoiseKernel) and isinstance(diffusion.schedule, NoiseSchedule)
    sampler = instantiate(cfg.sampler)(diffusion)
    assert isinstance(sampler, Sampler)


def test_config_options_match_registries() -> None:
    """Each registered kernel/schedule/sampler has a config file of the same name, and vice versa."""
    for folder, family in (("kernel", NoiseKernel), ("schedule", NoiseSchedule), ("sampler", Sampler)):
        files = {p.stem for p in (CONF / folder).glob("*.yaml")}
        names = set(family.registry)
        assert files == names, f"conf/{folder}: {sorted(files)} vs registry {sorted(names)}"


def test_paper_defaults() -> None:
    """Without an experiment, the composed config is the paper's method (the authors' code is opt-in)."""
    cfg = _compose(["denoiser.cond_dim=14", *NO_HYDRA])
    d = cfg.diffusion
    assert (d.score, d.output, d.loss, d.prior) == ("surrogate", "score", "tangent_l2", "kernel")
    assert OmegaConf.select(cfg, "schedule._target_").endswith("LinearSchedule")
    assert OmegaConf.select(cfg, "sampler._target_").endswith("GeodesicRandomWalk")


@pytest.mark.parametrize(("experiment", "width"), [("toy_so3", 9), ("toy_se3", 12)])
def test_matrix_pose_input(experiment: str, width: int) -> None:
    """``module.pose_input=matrix`` feeds the top 3 rows of X̃ and sizes the denoiser to match."""
    cfg = _compose([f"+experiment={experiment}", "module.pose_input=matrix", *NO_HYDRA])
    module = instantiate(cfg.module)
    assert cfg.denoiser.in_dim == width and cfg.denoiser.out_dim == module.group.dim
    x = module.group.sample_uniform((2, 3), generator=torch.Generator().manual_seed(0))
    feats = module.pose_features(x)
    assert feats.shape == (2, 3, width)
    torch.testing.assert_close(feats, x[..., :3, :].flatten(-2))
    data = instantiate(cfg.data)
    data.setup("fit")
    batch = next(iter(data.train_dataloader()))
    assert torch.isfinite(module.training_step({k: v[:2] for k, v in batch.items()}, 0))
    with pytest.raises(ValueError, match="tangent, matrix"):
        pose_input_dim(module.group, "quaternion")
    with pytest.raises(ValueError, match="tangent, matrix"):
        PoseDiffusionModule(module.diffusion, module.denoiser, module.sampler, pose_input="quaternion")
