"""``posediff eval ckpt_path=CKPT``: metrics of a checkpoint on its (or another) test set; ``metrics.json``
and ``metrics.md`` in the run folder. Step counts are a sampler option (``sampler.num_steps``; a
multirun over them gives one table, ``report.md``)."""

from __future__ import annotations

from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..._io import atomic_write_json, atomic_write_text
from ...evaluation import evaluate_data, write_results
from ...evaluation.report import run_table
from ...options import whole
from ..errors import user_input
from ..runs import checkpoint_run, device, likelihood_options, test_data


def run(cfg: DictConfig) -> int:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    with user_input(ValueError, FileNotFoundError, RuntimeError):
        whole(cfg.num_samples, "num_samples")
        if cfg.max_inputs is not None:
            whole(cfg.max_inputs, "max_inputs")
        dev = device(str(cfg.device))
        likelihood = likelihood_options(cfg.get("eval") or {})
        module, run_cfg = checkpoint_run(cfg)
        datamodule = test_data(run_cfg)
    print(datamodule.describe())
    module.to(dev)
    result = evaluate_data(
        module,
        datamodule,
        num_samples=int(cfg.num_samples),
        num_steps=None,
        seed=int(cfg.seed),
        max_inputs=cfg.max_inputs,
        vsd=bool(cfg.get("vsd", True)),
        **likelihood,
    )
    write_results(result, datamodule, out_dir)
    result.update(
        ckpt_path=str(cfg.ckpt_path),
        device=str(dev),
        data=OmegaConf.to_container(run_cfg.data, resolve=True),
        sampler_config=OmegaConf.to_container(run_cfg.module.sampler, resolve=True),
    )
    atomic_write_json(out_dir / "metrics.json", result)
    table = run_table(result)
    atomic_write_text(out_dir / "metrics.md", table)
    print(table)
    print(f"metrics: {out_dir / 'metrics.json'}")
    if "bop19_csv" in result:
        print(f"BOP19 estimates: {result['bop19_csv']} (for the BOP toolkit's eval_bop19_pose.py)")
    return 0
