"""Checkpoints written before the move into ``posediff.models`` / ``posediff.training`` still load: their
stored configs name the old dotted paths (``posediff.module.PoseDiffusionModule``,
``posediff.callbacks.ProgressLog``, ...), which the allow-list's one table of old → new names
(:data:`posediff.config.allowlist.RENAMED`) reads as the new ones."""

from pathlib import Path

import pytest
import torch

import posediff
from posediff.cli import main
from posediff.config.allowlist import (
    RENAMED,
    TRAINER_ONLY,
    UntrustedConfigError,
    buildable_targets,
    check_config,
    upgrade_config,
)
from posediff.models import CONFIG_KEY, CheckpointError, PoseDiffusionModule

TOY = ["+experiment=toy_so3", "trainer.max_steps=2", "trainer.val_check_interval=2",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip

OLD_NAMES = {new: old for old, new in RENAMED.items()}


def _renamed_back(node):  # noqa: ANN001, ANN202 - plain config data
    """``node`` with every new dotted name written the way the old layout wrote it."""
    if isinstance(node, dict):
        out = {k: _renamed_back(v) for k, v in node.items()}
        if out.get("_target_") in OLD_NAMES:
            out["_target_"] = OLD_NAMES[out["_target_"]]
        return out
    if isinstance(node, list):
        return [_renamed_back(v) for v in node]
    return node


@pytest.fixture(scope="module")
def old_ckpt(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A toy checkpoint (new names) and the same file with its config in the old names."""
    out = tmp_path_factory.mktemp("fit") / "run"
    assert main(["fit", *TOY, f"hydra.run.dir={out}"]) == 0
    new = out / "checkpoints" / "last.ckpt"
    raw = torch.load(new, weights_only=True, map_location="cpu")
    raw[CONFIG_KEY] = _renamed_back(raw[CONFIG_KEY])
    raw["hyper_parameters"][CONFIG_KEY] = raw[CONFIG_KEY]
    assert raw[CONFIG_KEY]["module"]["_target_"] == "posediff.module.PoseDiffusionModule"
    assert any(c.get("_target_", "").startswith("posediff.callbacks.")
               for c in raw[CONFIG_KEY]["trainer"]["callbacks"])  # fmt: skip
    old = out / "old_names.ckpt"
    torch.save(raw, old)
    return new, old


def test_a_checkpoint_with_the_old_names_loads_as_the_new_classes(old_ckpt: tuple[Path, Path]) -> None:
    new, old = old_ckpt
    a, b = posediff.load_checkpoint(new), posediff.load_checkpoint(old)
    assert type(b) is PoseDiffusionModule and not b.training
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert ka == kb and torch.equal(va, vb)
    assert b.config["module"]["_target_"] == "posediff.models.PoseDiffusionModule"  # read as the new name
    assert type(PoseDiffusionModule.load_from_checkpoint(old)) is PoseDiffusionModule


def test_eval_reads_a_checkpoint_with_the_old_names(old_ckpt: tuple[Path, Path], tmp_path: Path) -> None:
    _, old = old_ckpt
    assert main(["eval", f"ckpt_path={old}", "num_samples=2", "sampler.num_steps=2",
                 f"hydra.run.dir={tmp_path / 'eval'}"]) == 0  # fmt: skip
    assert (tmp_path / "eval" / "metrics.json").is_file()


def test_every_old_name_maps_to_a_buildable_class() -> None:
    assert set(RENAMED.values()) <= buildable_targets() | TRAINER_ONLY
    assert not set(RENAMED) & set(RENAMED.values())
    check_config({"module": {"_target_": "posediff.module.PoseDiffusionModule"}})  # old names pass the check
    assert upgrade_config({"a": [{"_target_": "posediff.callbacks.ProgressLog"}]}) == {
        "a": [{"_target_": "posediff.training.callbacks.ProgressLog"}]
    }


def test_the_table_opens_no_other_door(old_ckpt: tuple[Path, Path], tmp_path: Path) -> None:
    """A name that was never posediff's is refused under the old layout too."""
    _, old = old_ckpt
    raw = torch.load(old, weights_only=True, map_location="cpu")
    raw[CONFIG_KEY]["module"]["_target_"] = "posediff.module.os.system"
    bad = tmp_path / "bad.ckpt"
    torch.save(raw, bad)
    with pytest.raises(CheckpointError, match="not a class posediff builds"):
        posediff.load_checkpoint(bad)
    with pytest.raises(UntrustedConfigError):
        check_config({"module": {"_target_": "posediff.module.os.system"}})
