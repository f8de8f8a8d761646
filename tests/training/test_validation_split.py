"""Honest model selection: the validation split (``val/loss``, which picks ``best.ckpt``) is held out
of the training data and is never the test split — toy, SYMSOL (shards and render) and BOP."""

from pathlib import Path

import numpy as np
import pytest
import torch

from posediff.data import SymmetryToyDataModule
from posediff.data.bop import BopDataModule
from posediff.data.bop import datamodule as bop_datamodule
from posediff.data.symsol import SymsolDataModule
from posediff.data.symsol.shards import SymsolShards, render_dataset


def _rotations(loader) -> torch.Tensor:  # noqa: ANN001
    return torch.cat([b["rotation"].reshape(-1, 9) for b in loader])


def _shared_rows(a: torch.Tensor, b: torch.Tensor) -> int:
    return int((torch.cdist(a.double(), b.double()) < 1e-9).any(1).sum())


def test_toy_validation_is_its_own_draw() -> None:
    dm = SymmetryToyDataModule("so3", num_train=64, num_test_per_shape=4, num_val_per_shape=3, batch_size=8)
    dm.setup("fit")
    assert len(dm.val) == 15 and len(dm.test) == 20
    val = _rotations(dm.val_dataloader())
    assert len(val) == 15
    assert _shared_rows(val, dm.train.rotation.reshape(-1, 9)) == 0
    assert _shared_rows(val, dm.test.rotation.reshape(-1, 9)) == 0


@pytest.fixture(scope="module")
def shards_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("symsolt")
    for split, n in (("train", 24), ("test", 4)):
        render_dataset(root, split=split, n_per_shape=n, image_size=16, shard_size=16, progress=False)
    return root


def test_symsol_shards_hold_out_training_samples(shards_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    dm = SymsolDataModule("symsolt", "uniform", root=str(shards_root), image_size=16, batch_size=4,
                          val_fraction=0.05, max_val=1000)  # fmt: skip
    dm.setup("fit")
    n = len(dm.train.shards)  # 120 training samples: the last 6 (5%) are validation
    read: list[tuple[str, int]] = []
    load = SymsolShards.load_shard

    def spy(self, k, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        read.append((self.path.name, int(k)))
        return load(self, k, *args, **kwargs)

    monkeypatch.setattr(SymsolShards, "load_shard", spy)
    val = torch.cat([b["index"] for b in dm.val_dataloader()]).tolist()
    assert val == list(range(n - 6, n))
    assert {name for name, _ in read} == {"train"}, "validation read the test split"
    assert {k for _, k in read} == {7}, "validation reads only the shard(s) holding it"
    read.clear()
    train = set()
    for _ in range(2):  # two epochs: the held-out samples never come up
        train |= set(torch.cat([b["index"] for b in dm.train_dataloader()]).tolist())
    assert train.isdisjoint(val) and len(train) > 100
    assert {name for name, _ in read} == {"train"}
    test = set(torch.cat([b["index"] for b in dm.test_dataloader()]).tolist())
    assert dm.test.shards.path.name == "test" and dm.val.shards.path.name == "train" and len(test) == 20


def test_symsol_render_validation_is_a_separate_seeded_draw() -> None:
    kw = {"mode": "render", "image_size": 16, "n_per_shape_train": 40, "n_per_shape_test": 3, "batch_size": 4}
    dm = SymsolDataModule("symsolt", "uniform", **kw)
    dm.setup("fit")
    assert len(dm.val) == 2 * 5  # 5% of 40 per shape
    val = torch.from_numpy(dm.val.poses.R.reshape(-1, 9))
    assert _shared_rows(val, torch.from_numpy(dm.train.poses.R.reshape(-1, 9))) == 0
    assert _shared_rows(val, torch.from_numpy(dm.test.poses.R.reshape(-1, 9))) == 0
    again = SymsolDataModule("symsolt", "uniform", **kw)
    again.setup("fit")
    assert np.array_equal(again.val.poses.R, dm.val.poses.R), "deterministic"
    capped = SymsolDataModule("symsolt", "uniform", **{**kw, "n_per_shape_train": 10_000}, max_val=50)
    assert capped.n_per_shape["val"] == 10
    with pytest.raises(ValueError, match="val_fraction"):
        SymsolDataModule("symsolt", "uniform", **kw, val_fraction=0.0)


def _images(instances) -> set[tuple[str, int, int]]:  # noqa: ANN001
    return {(i.split, i.scene_id, i.im_id) for i in instances}


def test_bop_validation_holds_out_training_images(bop_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    dm = BopDataModule(
        str(bop_root), image_size=32, batch_size=4, num_workers=0, augment=None, val_fraction=0.1
    )
    dm.setup("fit")
    train, val, test = _images(dm.train.instances), _images(dm.val.instances), _images(dm.test.instances)
    assert val and train.isdisjoint(val), "whole images are held out"
    assert {s for s, _, _ in val} <= set(dm.train_splits) and dm.test_split not in {s for s, _, _ in val}
    assert not val & test
    n_images = len(train | val)
    assert len(val) == max(1, round(0.1 * n_images))
    assert f"{len(dm.val)} of them held out" in dm.summary_line()
    read: list[str] = []
    rgb = bop_datamodule.read_rgb
    monkeypatch.setattr(bop_datamodule, "read_rgb", lambda p: read.append(str(p)) or rgb(p))
    batches = list(dm.val_dataloader())
    assert sum(len(b["index"]) for b in batches) == len(dm.val)
    assert read and not any(f"/{dm.test_split}/" in p for p in read), "validation read the test split"
    assert all(not b["image"].isnan().any() for b in batches)
    # the translation statistics are the training instances' alone
    ref = BopDataModule(str(bop_root), image_size=32, val_fraction=0.1)
    ref.fit_translation_stats(dm.train.instances)
    assert ref.encoding.stats() == dm.encoding.stats()
    both = BopDataModule(str(bop_root), image_size=32, val_fraction=0.1)
    both.fit_translation_stats(bop_datamodule.InstanceTable.concat([dm.train.instances, dm.val.instances]))
    assert both.encoding.stats() != dm.encoding.stats()
    again = BopDataModule(str(bop_root), image_size=32, val_fraction=0.1)
    again.setup("fit")
    assert _images(again.val.instances) == val, "deterministic"
