"""Cluster sweeps: the Hydra submitit launcher's configs compose with posediff's (no SLURM here to run
them; docs/cluster.md)."""

import pytest
from hydra import compose, initialize_config_dir

from posediff.cli import config_dir

pytest.importorskip("hydra_plugins.hydra_submitit_launcher")

SLURM = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"


def _compose(name: str, overrides: list[str]):  # noqa: ANN202
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name=name, overrides=overrides, return_hydra_config=True)


def test_an_eval_sweep_goes_to_slurm() -> None:
    for launcher in ("submitit_slurm", "posediff_slurm"):
        cfg = _compose(
            "eval", ["ckpt_path=x.ckpt", f"hydra/launcher={launcher}", "hydra.launcher.partition=gpu"]
        )
        assert cfg.hydra.launcher._target_ == SLURM and cfg.hydra.launcher.partition == "gpu"
    cfg = _compose("eval", ["ckpt_path=x.ckpt", "hydra/launcher=posediff_slurm"])
    assert cfg.hydra.launcher.timeout_min == 1440 and cfg.hydra.launcher.gpus_per_node == 1
    assert str(cfg.hydra.launcher.submitit_folder).endswith("/.submitit/%j")


def test_a_multi_node_ddp_fit_composes() -> None:
    cfg = _compose(
        "fit",
        ["+experiment=tless_se3", "hydra/launcher=posediff_slurm", "trainer=ddp", "trainer.devices=4",
         "trainer.num_nodes=2", "hydra.launcher.nodes=2", "hydra.launcher.tasks_per_node=4",
         "hydra.launcher.gpus_per_node=4"],
    )  # fmt: skip
    assert cfg.trainer.strategy == "ddp" and cfg.trainer.num_nodes == 2 and cfg.trainer.devices == 4
    launcher = cfg.hydra.launcher
    assert launcher._target_ == SLURM and launcher.nodes == 2 and launcher.tasks_per_node == 4


def test_the_cli_passes_plugin_launchers_through() -> None:
    from posediff.cli import _unknown_config_choice

    assert _unknown_config_choice(["hydra/launcher=submitit_slurm"], config_dir()) is None
    assert "available" in (_unknown_config_choice(["sampler=nope"], config_dir()) or "")
