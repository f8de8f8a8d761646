"""The BOP reader and the per-instance crops on the project's BOP fixture (``bop_root`` in conftest)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from posediff.data.bop import (
    BopDataModule,
    BopFormatError,
    BopModels,
    BopSplit,
    HardAugment,
    read_targets,
    target_instances,
)
from posediff.data.bop.reader import read_mask


@pytest.fixture(scope="module")
def dm(bop_root: Path) -> BopDataModule:
    d = BopDataModule(str(bop_root), image_size=64, batch_size=4, num_workers=0, augment=None)
    d.setup()
    return d


def test_models(bop_root: Path) -> None:
    models = BopModels(bop_root)
    assert models.obj_ids == [1, 2, 3]
    info = json.loads((bop_root / "models" / "models_info.json").read_text())
    assert models.diameter(2) == pytest.approx(info["2"]["diameter"])
    pts = models.points(1)
    assert pts.ndim == 2 and pts.shape[1] == 3
    # the diameter is the largest distance between model points
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1).max() if len(pts) < 3000 else models.diameter(1)
    assert d == pytest.approx(models.diameter(1), rel=1e-6)
    R, t = models.symmetries(2)
    assert len(R) == 4 and np.allclose(R[0], np.eye(3))  # box: identity + three half turns
    R, _ = models.symmetries(1)
    assert len(R) == 2 * 315  # cylinder: ceil(π / 0.01) rotations, with and without the flip
    assert len(models.symmetries(3)[0]) == 1
    with pytest.raises(
        BopFormatError, match=r"\[7\] have no entry in .*models_info.json \(it has \[1, 2, 3\]\)"
    ):
        models.check([1, 7], "data.obj_ids")


def test_split_reads_every_instance(bop_root: Path) -> None:
    models = BopModels(bop_root)
    split = BopSplit(bop_root, "test_primesense", models)
    n = 0
    for scene in sorted((bop_root / "test_primesense").iterdir()):
        gt = json.loads((scene / "scene_gt.json").read_text())
        n += sum(len(v) for v in gt.values())
    assert len(split) == n > 0
    inst = split.instances[0]
    assert inst.rgb_path.is_file() and inst.depth_path.is_file() and inst.mask_visib_path.is_file()
    assert inst.image_hw == (180, 240)
    # the pose projects the object's origin into its box
    p = inst.K @ inst.t
    x, y, w, h = inst.bbox_obj
    assert x <= p[0] / p[2] <= x + w and y <= p[1] / p[2] <= y + h
    assert read_mask(inst.mask_visib_path).sum() == inst.px_count_visib
    only2 = BopSplit(bop_root, "test_primesense", models, obj_ids=[2])
    assert {i.obj_id for i in only2.instances} == {2}


def test_targets_are_the_most_visible_instances(bop_root: Path) -> None:
    models = BopModels(bop_root)
    targets = read_targets(bop_root / "test_targets_bop19.json")
    split = BopSplit(bop_root, "test_primesense", models)
    chosen = target_instances(split.instances, targets)
    assert len(chosen) == sum(t.inst_count for t in targets)
    for t in targets:
        same = [
            i for i in split.instances if (i.scene_id, i.im_id, i.obj_id) == (t.scene_id, t.im_id, t.obj_id)
        ]
        picked = [i for i in chosen if i in same]
        rest = [i for i in same if i not in picked]
        assert min(i.visib_fract for i in picked) >= max((i.visib_fract for i in rest), default=0.0)


def test_bad_input_is_one_line(bop_root: Path, tmp_path: Path) -> None:
    with pytest.raises(BopFormatError, match=r"missing BOP models folder .*nowhere.*make-bop"):
        BopModels(tmp_path / "nowhere")
    models = BopModels(bop_root)
    with pytest.raises(BopFormatError, match=r"missing BOP split .*train_real \(folders there: .*models"):
        BopSplit(bop_root, "train_real", models)
    # a malformed scene: the file and the key are named
    root = tmp_path / "broken"
    shutil.copytree(bop_root, root)
    scene = sorted((root / "test_primesense").iterdir())[0]
    gt = json.loads((scene / "scene_gt.json").read_text())
    first = next(iter(gt))
    del gt[first][0]["cam_t_m2c"]
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    with pytest.raises(
        BopFormatError, match=rf"scene_gt.json: image {first} instance 0 has no key 'cam_t_m2c'"
    ):
        BopSplit(root, "test_primesense", models)
    (scene / "scene_gt.json").write_text("{not json")
    with pytest.raises(BopFormatError, match=r"scene_gt.json: not valid JSON"):
        BopSplit(root, "test_primesense", models)
    # an object without models_info
    info = json.loads((root / "models" / "models_info.json").read_text())
    del info["3"]
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    shutil.copy(bop_root / "test_primesense" / scene.name / "scene_gt.json", scene / "scene_gt.json")
    with pytest.raises(BopFormatError, match=r"object 3, which has no entry in .*models_info.json"):
        BopSplit(root, "test_primesense", BopModels(root))
    with pytest.raises(ValueError, match="data.root is not set"):
        BopDataModule("")


def test_samples_round_trip_to_the_ground_truth(dm: BopDataModule) -> None:
    assert dm.encoding.fitted and dm.train is not None and dm.test is not None
    for ds in (dm.train, dm.test):
        for i in range(0, len(ds), max(1, len(ds) // 5)):
            s = ds[i]
            assert s["image"].shape == (3, 64, 64) and s["mask"].shape == (64, 64)
            assert float((s["image"] * ~s["mask"]).abs().max()) == 0.0  # masked to the visible part
            assert s["mask"].any()
            R, t = dm.encoding.decode(
                s["pose"][:3, :3].double(), s["pose"][:3, 3].double(), s["K"].double(), s["centre"].double(),
                s["side"].double(), 64,
            )  # fmt: skip
            assert_close(t.float(), s["translation"], atol=1e-2, rtol=1e-5)
            assert_close(R.float(), s["rotation"], atol=1e-5, rtol=0)
            inst = ds.instances[int(s["index"])]
            assert np.allclose(inst.t, s["translation"].numpy(), atol=1e-3)


def test_test_crops_are_centred_and_training_crops_jitter(dm: BopDataModule) -> None:
    s = dm.test[0]
    inst = dm.test.instances[0]
    x, y, w, h = inst.bbox_obj
    assert_close(s["centre"], torch.tensor([x + w / 2, y + h / 2], dtype=torch.float32))
    assert float(s["side"]) == pytest.approx(min(1.5 * max(w, h), 240.0))
    # training crops jitter, drawn from (seed, epoch, index): reproducible (any worker, after a
    # resume), the same whatever the global RNG, and new every epoch
    a = dm.train[0]
    torch.manual_seed(123)
    assert torch.equal(dm.train[0]["centre"], a["centre"]) and float(dm.train[0]["side"]) == float(a["side"])
    centred, _ = dm.train.box(dm.train.instances[0], None)
    assert not np.allclose(a["centre"].numpy(), centred, atol=1e-3)
    dm.train.set_epoch(1)
    b = dm.train[0]
    dm.train.set_epoch(0)
    assert not torch.equal(a["centre"], b["centre"]) or float(a["side"]) != float(b["side"])


def test_translation_statistics_standardise_the_training_split(dm: BopDataModule) -> None:
    torch.manual_seed(0)
    deltas = torch.stack([dm.train[i]["pose"][:3, 3] for i in range(len(dm.train)) for _ in range(2)])
    assert deltas.mean(0).abs().max() < 0.5 and (deltas.std(0) - 1).abs().max() < 0.5


def test_filter_and_skipped_targets(bop_root: Path) -> None:
    d = BopDataModule(
        str(bop_root),
        image_size=32,
        min_visible_px=10**9,
        translation_stats={"mean": [0, 0, 1], "std": [1, 1, 1]},
    )
    d.setup("test")
    assert len(d.test) == 0 and len(d.skipped) == len(d.targets) > 0
    assert f"{len(d.targets)} targets, {len(d.skipped)} skipped" in d.summary_line()
    d2 = BopDataModule(str(bop_root), image_size=32, max_test_instances=3)
    with pytest.raises(BopFormatError, match="translation statistics are unknown"):
        d2.setup("test")


def test_augmentation_keeps_the_background_black(dm: BopDataModule) -> None:
    batch = next(iter(dm.train_dataloader()))
    aug = HardAugment(p=1.0)
    out = aug(batch["image"]) * batch["mask"][:, None]
    assert (
        out.shape == batch["image"].shape
        and float(out[~batch["mask"][:, None].expand_as(out)].abs().max()) == 0.0
    )
    assert not torch.equal(out, batch["image"])
    assert 0.0 <= float(out.min()) and float(out.max()) <= 1.0


def test_rotation_only_group(bop_root: Path) -> None:
    d = BopDataModule(str(bop_root), image_size=32, group="so3")
    d.setup("fit")
    assert d.train[0]["pose"].shape == (3, 3)


def test_instance_table_columns_and_records(bop_root: Path) -> None:
    from posediff.data.bop.datamodule import keep_instance, keep_mask
    from posediff.data.bop.reader import InstanceTable

    models = BopModels(bop_root)
    a = BopSplit(bop_root, "train_pbr", models).instances
    b = BopSplit(bop_root, "train_primesense", models).instances
    both = InstanceTable.concat([a, b])
    assert len(both) == len(a) + len(b) and isinstance(both, InstanceTable)
    assert both[len(a)] == b[0] and both[-1] == b[-1] and both[0] != b[0]
    assert both[len(a)].rgb_path == b[0].rgb_path and both[0].rgb_path.suffix == ".jpg"
    assert both[-1].rgb_path.suffix == ".png" and len({both[0], a[0]}) == 1  # hashable by ground truth
    mask = keep_mask(both, 64, 0.5)
    assert mask.tolist() == [keep_instance(i, 64, 0.5) for i in both]
    sub = both.take(mask)
    assert len(sub) == int(mask.sum()) and all(keep_instance(i, 64, 0.5) for i in sub)
    assert len(both[2:5]) == 3 and both[2:5][0] == both[2]
    with pytest.raises(IndexError):
        both[len(both)]
    assert len(InstanceTable.concat([])) == 0


def test_dzi_many_matches_dzi() -> None:
    from posediff.data.bop.roi import clip_box, clip_boxes, dzi, dzi_many

    boxes = np.array([[100.0, 50.0, 60.0, 40.0], [-20.0, 500.0, 700.0, 90.0]])
    hw = np.array([[540, 720], [540, 720]])
    assert np.allclose(clip_boxes(boxes, hw), np.stack([clip_box(b, (540, 720)) for b in boxes]))
    c, s = dzi_many(boxes, hw, np.random.default_rng(3))
    for k in range(2):
        r = np.random.default_rng(0)
        lo = dzi(boxes[k], (540, 720), rng=r, shift=0.0, scale=0.0)
        assert np.all(np.abs(c[k] - lo[0]) <= 0.25 * boxes[k, 2:] + 1e-9)
        m = boxes[k, 2:].max()
        assert min(1.125 * m, 720.0) - 1e-9 <= s[k] <= min(1.875 * m, 720.0) + 1e-9


def test_a_renderer_released_while_another_draws_keeps_its_context() -> None:
    """A renderer's __del__ may run (garbage collection) in the middle of another renderer's draw;
    releasing its EGL context must leave the drawing one current (it used to leave none: "Attempt to
    retrieve context when no valid context" in the next GL call)."""
    import trimesh

    from posediff.data.bop.render import BopRenderer

    K = np.array([[300.0, 0, 80], [0, 300, 60], [0, 0, 1]])
    mesh = trimesh.creation.box((40, 30, 20))
    a, b = BopRenderer(160, 120), BopRenderer(160, 120)
    a.add_model(1, mesh), b.add_model(1, mesh)
    ref = b.render_depth(1, np.eye(3), [0, 0, 500], K)
    a._ready()
    inner = a._gl.renderer._renderer
    draw = inner.render

    def render_while_b_is_collected(*args, **kwargs):  # noqa: ANN202, ANN002, ANN003
        b.close()
        return draw(*args, **kwargs)

    inner.render = render_while_b_is_collected
    depth = a.render_depth(1, np.eye(3), [0, 0, 500], K)
    assert_close(torch.from_numpy(depth), torch.from_numpy(ref))
    a.close()
