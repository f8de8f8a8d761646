"""``posediff fit``: train ``cfg.module`` on ``cfg.data`` with ``cfg.trainer``, then evaluate it;
``posediff pretrain``: the same with the ``pretrain`` experiment, then the encoder's weights to a file.

Writes ``metrics.json`` and ``metrics.md`` (atomically) in the Hydra run folder: the untrained model's
metrics (``before``), the training loss curve summary and, for every sampler in ``eval.samplers`` and
every step count in ``eval.num_steps``, per-shape spread / translation error / coverage.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ..._io import atomic_write_bytes, atomic_write_json, atomic_write_text
from ...evaluation import evaluate_data, write_results
from ...evaluation.report import fit_markdown, headline
from ...models import CONFIG_KEY, CheckpointError, PoseModule, check_compatible, read_checkpoint
from ...options import whole
from ...training.trainer import build_trainer
from ..errors import InputError, user_input
from ..runs import experiment_name, likelihood_options, mean


def run(cfg: DictConfig, *, encoder_out: Path | None = None) -> int:
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    with user_input():  # missing / malformed data, a missing weights file, a bad option: one line
        likelihood = likelihood_options(cfg.eval)  # refused before training, not after it
        datamodule = instantiate(cfg.data)
        datamodule.setup("fit")
        print(datamodule.describe())
        module = instantiate(cfg.module)
        if not isinstance(module, PoseModule):
            raise TypeError(f"module config builds {type(module).__name__}, not a PoseModule")
        eval_samplers = check_fit_options(
            cfg, module
        )  # every option checked now, not after hours of training
    module.config = OmegaConf.to_container(cfg, resolve=True)
    if cfg.ckpt_path is not None:
        check_resume(cfg.ckpt_path, module, datamodule)
    trainer = build_trainer(cfg.trainer, ema=cfg.get("ema"))
    stored = datamodule.checkpoint_data()  # e.g. BOP: the training split's translation statistics
    if stored:
        module.config["data"].update(stored)
        for key, value in stored.items():
            print(f"stored with the checkpoint: data.{key} = {value}")
    results: dict[str, Any] = {"experiment": experiment_name(), "diffusion": module.diffusion.describe()}
    # DDP ranks > 0 re-run this function; they only train (the trainer knows its rank from the launcher)
    if cfg.eval.before and trainer.is_global_zero:
        module.to(trainer.strategy.root_device)
        results["before"] = evaluate_data(
            module,
            datamodule,
            num_samples=int(cfg.eval.get("before_num_samples") or cfg.eval.num_samples),
            num_steps=int(max(cfg.eval.num_steps)),
            seed=int(cfg.eval.seed),
            log_likelihood=False,  # the untrained row: its density is the prior's, whatever the image
        )
        results["before"].pop("estimates", None)
        print(f"before training: {headline(results['before'])}")
    start = time.perf_counter()
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.ckpt_path)
    except SystemExit:  # Lightning exits after a graceful Ctrl-C; report it as the interrupt it was
        if trainer.interrupted:
            last = out_dir / "checkpoints" / "last.ckpt"
            hint = f"resume with ckpt_path={last}" if last.is_file() else "no checkpoint was written yet"
            raise KeyboardInterrupt(f"fit stopped at step {trainer.global_step}; {hint}") from None
        raise
    if not trainer.is_global_zero:
        return 0
    losses = module.loss_history
    results["train"] = {"steps": int(trainer.global_step), "seconds": time.perf_counter() - start,
                        "loss_first": mean(losses[:50]), "loss_last": mean(losses[-50:])}  # fmt: skip
    results["after"] = evaluate_after(cfg, module, datamodule, eval_samplers, likelihood, out_dir)
    json.dumps(results)  # fail here, before writing, if something is not serialisable
    text = fit_markdown(results)
    atomic_write_text(out_dir / "metrics.md", text)
    path = atomic_write_json(out_dir / "metrics.json", results)
    print(text)
    print(f"metrics: {path} (and metrics.md)")
    if encoder_out is not None:
        print(f"encoder weights: {save_encoder(module, encoder_out, cfg, results)} "
              "(use: encoder.weights=<that file>)")  # fmt: skip
    return 0


def pretrain(cfg: DictConfig) -> int:
    """``posediff pretrain``: ``fit`` with the ``pretrain`` experiment (symmetry-aware regression of the
    :class:`~posediff.nn.PoseEncoder` on posediff's renders), then the encoder's weights to ``cfg.out``
    (atomically) for ``encoder.weights=...``."""
    if not cfg.get("out"):
        raise InputError("out= is empty; give the file to write the encoder's weights to")
    return run(cfg, encoder_out=Path(str(cfg.out)))


def check_fit_options(cfg: DictConfig, module: Any) -> dict[str, Any]:
    """Refuse bad numeric options before training (one line naming the key); the evaluation
    samplers by name (``None``: the module's own), built now so a bad one fails before training."""
    levels = module.diffusion.schedule.num_levels
    whole(cfg.eval.num_samples, "eval.num_samples")
    steps = list(cfg.eval.num_steps) if cfg.eval.num_steps is not None else []
    if not steps:
        raise ValueError("eval.num_steps is empty; give step counts, e.g. eval.num_steps=[100]")
    for s in steps:
        whole(s, "eval.num_steps", 1, levels)
    whole(cfg.trainer.get("max_steps", -1), "trainer.max_steps", allow=(-1,))
    samplers: dict[str, Any] = {}
    for name, sampler_cfg in (cfg.eval.samplers or {"default": None}).items():
        samplers[name] = instantiate(sampler_cfg)(module.diffusion) if sampler_cfg is not None else None
    return samplers


def check_resume(path: Any, module: PoseModule, datamodule: Any) -> None:
    """Refuse (one line) resuming a checkpoint of another group, other shapes or another architecture."""
    try:
        stored = read_checkpoint(path)
        check_compatible(stored[CONFIG_KEY], group=module.group.name,
                         shapes=list(getattr(datamodule, "shapes", [])) or None, where=f"checkpoint {path}")  # fmt: skip
        have = module.state_dict()
        for key in sorted(set(stored["state_dict"]) | set(have)):
            a, b = stored["state_dict"].get(key), have.get(key)
            if a is None or b is None or tuple(a.shape) != tuple(b.shape):
                there = "absent" if a is None else f"{tuple(a.shape)}"
                here = "absent" if b is None else f"{tuple(b.shape)}"
                raise CheckpointError(
                    f"checkpoint {path} was trained with another architecture ({key}: {there} in the "
                    f"checkpoint, {here} with this config); resume with the settings it was trained with "
                    "(posediff fit --cfg job shows yours) or start a new run"
                )
    except CheckpointError as e:
        raise InputError(f"cannot resume: {e}") from None


def evaluate_after(cfg: DictConfig, module: PoseModule, datamodule: Any, samplers: dict[str, Any],
                   likelihood: dict[str, Any], out_dir: Path) -> dict[str, Any]:  # fmt: skip
    """The trained model at every sampler of ``eval.samplers`` and step count of ``eval.num_steps``
    (BOP data: each one's results CSV in the run folder)."""
    after: dict[str, Any] = {}
    for name, sampler in samplers.items():
        after[name] = {}
        for steps in cfg.eval.num_steps:
            res = evaluate_data(module, datamodule, num_samples=int(cfg.eval.num_samples), num_steps=int(steps),
                                sampler=sampler, seed=int(cfg.eval.seed), **likelihood)  # fmt: skip
            csv = write_results(res, datamodule, out_dir, f"{name}_{int(steps)}steps")
            if csv is not None:
                print(f"BOP19 estimates: {csv}")
            after[name][str(int(steps))] = res
    return after


def save_encoder(module: Any, path: Path, cfg: DictConfig, results: dict[str, Any]) -> Path:
    """The encoder's state dict and what made it, as a ``weights_only``-loadable file (temp name, rename)."""
    after = next(iter(results.get("after", {}).values()), {})
    res = next(iter(after.values()), {})
    info = {
        "experiment": experiment_name(),
        "encoder": OmegaConf.to_container(cfg.encoder, resolve=True),
        "data": {"root": str(cfg.data.get("root")), "image_size": int(cfg.data.image_size)},
        "train": results.get("train", {}),
        "spread_deg": {k: float(v.get("spread_deg", float("nan"))) for k, v in res.get("shapes", {}).items()},
    }
    buf = io.BytesIO()
    state = {k: v.detach().cpu().clone() for k, v in module.encoder.state_dict().items()}
    torch.save({"encoder_state_dict": state, "posediff_pretrain": info}, buf)
    return atomic_write_bytes(path, buf.getvalue())
