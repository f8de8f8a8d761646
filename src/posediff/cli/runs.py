"""What the commands share about a run: its device, the experiment's name, the checkpoint it reads
(with the command's ``group`` / ``data`` / ``sampler`` choices applied) and its test data."""

from __future__ import annotations

from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf

from ..models import CONFIG_KEY, PoseModule, check_compatible, module_from_checkpoint, read_checkpoint
from .errors import user_input


def device(name: str) -> torch.device:
    """``auto`` (CUDA when there is one), ``cpu``, ``cuda``, ``cuda:1`` …; refused when CUDA is asked for
    and absent."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name} but no CUDA device is available (use device=cpu or auto)")
    return dev


def experiment_name() -> str:
    """The ``+experiment=`` of this Hydra run (``none`` without one or outside Hydra)."""
    try:
        return str(HydraConfig.get().runtime.choices.get("experiment", "none"))
    except ValueError:
        return "none"


def mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def likelihood_options(eval_cfg: Any) -> dict[str, Any]:
    """``eval.log_likelihood`` (null: the data's default, on for SYMSOL) and ``eval.log_likelihood_steps``."""
    flag = eval_cfg.get("log_likelihood")
    if flag is not None and not isinstance(flag, bool):
        raise ValueError(f"eval.log_likelihood must be true, false or null, got {flag!r}")
    # its bounds are posediff.options' (checked with every option before the command runs)
    return {"log_likelihood": flag, "log_likelihood_steps": int(eval_cfg.get("log_likelihood_steps", 50))}


def _images_at_checkpoint_size(run: DictConfig, stored: dict[str, Any], command: str) -> None:
    """Data read from image files at another size than the checkpoint's encoder is resized to the
    checkpoint's size (one line says so); rendered shards of another size stay refused by their reader."""
    want = (stored.get("data") or {}).get("image_size")
    have = run.data.get("image_size")
    if want is None or have is None or int(have) == int(want) or "_target_" not in run.data:
        return
    try:
        resizes = bool(getattr(get_class(str(run.data._target_)), "resizes_images", False))
    except Exception:  # an unknown target fails later with its own one-line message
        return
    if resizes:
        print(
            f"{command}: the checkpoint's encoder takes {int(want)} px images; "
            f"resizing the data's images to {int(want)} px (data.image_size was {int(have)})"
        )
        run.data.image_size = int(want)


def checkpoint_run(cfg: DictConfig, command: str = "posediff eval") -> tuple[PoseModule, DictConfig]:
    """The module of ``cfg.ckpt_path`` and its run config with the command's ``group`` / ``data`` /
    ``sampler`` choices applied (a data mapping without ``_target_`` overrides single keys); the
    module's sampler is the resulting one."""
    ckpt = read_checkpoint(cfg.ckpt_path)
    config = ckpt[CONFIG_KEY]
    run = OmegaConf.create(config)
    data = cfg.get("data")
    if data:
        d = OmegaConf.to_container(data, resolve=False)
        run.data = d if "_target_" in d else OmegaConf.merge(run.data, d)
        _images_at_checkpoint_size(run, config, command)
    group = str(get_class(cfg.group._target_).name) if cfg.get("group") is not None else None
    shapes = list(run.data.shapes) if "shapes" in run.data else None
    check_compatible(config, group=group, shapes=shapes, where=f"checkpoint {cfg.ckpt_path}")
    module = module_from_checkpoint(ckpt, cfg.ckpt_path)
    sampler = cfg.get("sampler")
    if sampler:
        s = OmegaConf.to_container(sampler, resolve=True)
        if "_target_" not in s:  # single keys over the stored sampler; null keeps the stored value
            s = {k: v for k, v in s.items() if v is not None}
        run.module.sampler = s if "_target_" in s else OmegaConf.merge(run.module.sampler, s)
    module.sampler = instantiate(run.module.sampler)(module.diffusion)  # bad num_steps: one-line ValueError
    return module, run


def test_data(run: DictConfig) -> Any:
    """The test data of a run config (``data.*`` as stored, with any overrides applied), set up."""
    with user_input():
        datamodule = instantiate(run.data)
        datamodule.setup("test")
    return datamodule
