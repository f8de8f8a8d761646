"""``posediff score csv=PATH data.root=DIR``: BOP19 scores of any results CSV on a BOP dataset's test
split (:func:`posediff.evaluation.bop.score_estimates`); ``metrics.json`` / ``metrics.md`` in the run
folder, as ``posediff eval``."""

from __future__ import annotations

import time
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ..._io import atomic_write_json, atomic_write_text
from ...evaluation.bop import read_results_file, score_estimates, scoring_setup
from ...evaluation.report import headline, run_table
from ..errors import user_input


def run(cfg: DictConfig) -> int:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    start = time.perf_counter()
    with user_input():
        rows = read_results_file(cfg.csv)
        if cfg.data is None or "_target_" not in cfg.data:
            raise ValueError("data= must name a BOP data config (data=tless, the default) with data.root=DIR")
        datamodule = instantiate(cfg.data)
        delta = scoring_setup(rows, datamodule, cfg.vsd_delta, data_name=str(cfg.data._target_))
    csv = Path(str(cfg.csv))
    images = {i.key[:2] for i in datamodule.targets}
    print(
        f"BOP data {datamodule.root}, {datamodule.test_split}: {len(datamodule.targets)} targets in "
        f"{len(images)} images; {len(rows)} estimates in {csv}"
    )
    result = score_estimates(datamodule, rows, vsd=bool(cfg.vsd), vsd_delta=delta)
    data = OmegaConf.to_container(cfg.data, resolve=True)
    result.update(
        csv=str(csv),
        seconds=time.perf_counter() - start,
        vsd_delta=delta,
        data={
            k: data.get(k)
            for k in ("root", "test_split", "targets", "models_dir", "eval_models_dir", "obj_ids")
        },
    )
    atomic_write_json(out_dir / "metrics.json", result)
    table = run_table(result)
    atomic_write_text(out_dir / "metrics.md", table)
    print(table)
    print(f"{headline(result)}; metrics: {out_dir / 'metrics.json'}")
    return 0
