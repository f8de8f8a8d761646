"""The in-process BOP evaluation end to end on the fixture, with oracle models whose answers are known."""

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from posediff.data.bop import BopDataModule
from posediff.evaluation.bop import evaluate_bop
from posediff.evaluation.report import run_table
from posediff.metrics.bop19 import read_bop19_csv, write_bop19_csv


class _Sampler:
    name = "oracle"
    num_steps = 1


class Oracle(nn.Module):
    """Returns the encoded ground truth of the test crops in loader order (optionally moved by
    ``shift_mm`` along the camera x axis, or turned by a symmetry of the object)."""

    def __init__(self, dm: BopDataModule, shift_mm: float = 0.0, turn: bool = False) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.zeros(()))
        self.sampler = _Sampler()
        self.cond_key = "image"
        poses = []
        for batch in dm.test_dataloader():
            R, t = batch["rotation"].double(), batch["translation"].double()
            if turn:  # right-multiply by the last of the model's symmetries (the identity for obj 3)
                S = torch.stack(
                    [torch.from_numpy(dm.models.symmetries(int(o))[0][-1]) for o in batch["obj_id"]]
                )
                R = R @ S
            t = t + torch.tensor([shift_mm, 0.0, 0.0], dtype=torch.float64)
            R_net, d = dm.encoding.encode(
                R, t, batch["K"].double(), batch["centre"].double(), batch["side"].double(), dm.image_size
            )
            x = torch.eye(4, dtype=torch.float64).repeat(len(R), 1, 1)
            x[:, :3, :3], x[:, :3, 3] = R_net, d
            poses.append(x)
        self.poses = torch.cat(poses)
        self.i = 0

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def sample(self, image, num_samples, num_steps=None, *, sampler=None, generator=None):  # noqa: ANN001, ANN201
        b = image.shape[0]
        x = self.poses[self.i : self.i + b]
        self.i += b
        return x[:, None].expand(b, num_samples, 4, 4).float()


@pytest.fixture(scope="module")
def dm(bop_root: Path) -> BopDataModule:
    d = BopDataModule(str(bop_root), image_size=32, batch_size=5, num_workers=0, augment=None)
    d.setup()
    return d


def test_perfect_estimates_score_one_except_the_skipped(dm: BopDataModule) -> None:
    res = evaluate_bop(Oracle(dm), dm, num_samples=2)
    n, skipped = res["targets"], res["skipped"]
    assert n == len(dm.targets) and skipped == len(dm.skipped) and res["inputs"] == n - skipped
    frac = (n - skipped) / n
    o = res["overall"]
    for key in ("AR_MSPD", "AR_MSSD", "AR_VSD", "AR", "recall_rot@2", "recall_trans@2cm", "recall_z@2cm"):
        assert o[key] == pytest.approx(frac, abs=1e-6), key
    assert set(res["shapes"]) <= {"obj_000001", "obj_000002", "obj_000003"}
    assert len(res["estimates"]) == n - skipped
    table = run_table(res)
    for col in ("| MSPD | MSSD | VSD | AR | R@2° |", "T@2cm", "x@2cm", "z@10cm", "BOP19 protocol"):
        assert col in table


def test_a_symmetric_pose_is_correct_and_a_shift_is_seen(dm: BopDataModule) -> None:
    turned = evaluate_bop(Oracle(dm, turn=True), dm, vsd=False)["overall"]
    perfect = evaluate_bop(Oracle(dm), dm, vsd=False)["overall"]
    for key in ("AR_MSPD", "AR_MSSD", "recall_rot@2", "recall_trans@2cm"):
        assert turned[key] == pytest.approx(perfect[key], abs=1e-6), key
    assert np.isnan(perfect["AR_VSD"])  # not computed
    shifted = evaluate_bop(Oracle(dm, shift_mm=30.0), dm)["overall"]
    frac = perfect["recall_rot@2"]
    assert shifted["recall_trans@2cm"] == 0.0 and shifted["recall_trans@5cm"] == pytest.approx(frac)
    assert shifted["recall_x@2cm"] == 0.0 and shifted["recall_y@2cm"] == pytest.approx(frac)
    assert shifted["recall_z@2cm"] == pytest.approx(frac) and shifted["recall_rot@2"] == pytest.approx(frac)
    assert shifted["AR_MSSD"] < perfect["AR_MSSD"] and shifted["AR_VSD"] < 1.0


def test_estimates_export_as_bop19_csv(dm: BopDataModule, tmp_path: Path) -> None:
    res = evaluate_bop(Oracle(dm), dm, vsd=False)
    path = write_bop19_csv(tmp_path / "posediff_fixture-test.csv", res["estimates"])
    back = read_bop19_csv(path)
    assert len(back) == len(res["estimates"])
    for e in back:  # each row is its target's pose (the oracle's float32 pose, decoded)
        same = [i for i in dm.targets if (i.scene_id, i.im_id, i.obj_id) == (e.scene_id, e.im_id, e.obj_id)]
        inst = min(same, key=lambda i: float(np.linalg.norm(i.t - np.asarray(e.t))))
        assert np.linalg.norm(inst.t - np.asarray(e.t)) < 0.5
        assert np.allclose(np.asarray(e.R).reshape(3, 3), inst.R, atol=1e-5)
    assert path.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"


def test_partial_runs_and_objects_without_estimates(bop_root: Path) -> None:
    probe = BopDataModule(
        str(bop_root), image_size=32, translation_stats={"mean": [0, 0, 1], "std": [1, 1, 1]}
    )
    probe.setup("test")
    counts = sorted(i.px_count_visib for i in probe.targets)
    d = BopDataModule(str(bop_root), image_size=32, batch_size=2, min_visible_px=counts[len(counts) // 2],
                      translation_stats={"mean": [0, 0, 1], "std": [1, 1, 1]})  # fmt: skip
    d.setup("test")
    assert 0 < len(d.skipped) < len(d.targets)
    res = evaluate_bop(Oracle(d), d, max_inputs=2, vsd=False)
    keys = [i.key for i in d.targets]
    kept_keys = [i.key for i in d.test.instances]
    last = keys.index(kept_keys[1])  # the second predicted target
    assert res["targets"] == last + 1 and res["inputs"] == 2
    assert res["skipped"] == sum(1 for i in d.targets[: last + 1] if i in d.skipped)
    full = evaluate_bop(Oracle(d), d, vsd=False)
    for row in full["shapes"].values():  # every object row has every recall (0 where nothing was estimated)
        assert all(f"recall_{a}@{c}cm" in row for a in ("trans", "x", "y", "z") for c in (2, 5, 10))
        assert all(f"recall_rot@{c}" in row for c in (2, 5, 10))


def test_decode_prediction_returns_camera_frame_poses_and_modes(dm: BopDataModule) -> None:
    from posediff.evaluation.predict import Prediction, decode_prediction
    from posediff.lie import SE3

    s = dm.test[0]
    x = s["pose"].double().expand(6, 4, 4).clone()
    K, c, side = s["K"].double(), s["centre"].double(), s["side"].double()

    def decode(p: torch.Tensor):  # noqa: ANN202
        lead = p.shape[:-2]
        return dm.encoding.decode(p[..., :3, :3], p[..., :3, 3], K.expand(*lead, 3, 3), c.expand(*lead, 2),
                                  side.expand(*lead), dm.image_size)  # fmt: skip

    pred = decode_prediction(
        Prediction(samples=x, modes=None, trajectory=x[None].expand(3, 6, 4, 4)), decode, SE3()
    )
    assert pred.samples.shape == (6, 4, 4) and pred.trajectory.shape == (3, 6, 4, 4)
    assert torch.allclose(pred.samples[:, :3, 3].float(), s["translation"].expand(6, 3), atol=1e-2)
    assert torch.allclose(pred.samples[:, :3, :3].float(), s["rotation"].expand(6, 3, 3), atol=1e-5)
    assert len(pred.modes) == 1 and float(pred.modes.weights[0]) == 1.0


def test_object_mean_is_the_mean_of_the_object_rows(dm: BopDataModule) -> None:
    res = evaluate_bop(Oracle(dm, shift_mm=30.0), dm, vsd=False)
    rows = list(res["shapes"].values())
    for key in ("AR_MSSD", "recall_trans@5cm", "recall_x@2cm"):
        assert res["object_mean"][key] == pytest.approx(float(np.mean([r[key] for r in rows])))
    assert "| mean of objects |" in run_table(res)


def test_eval_and_score_agree_on_the_csv_eval_writes(
    dm: BopDataModule, bop_root: Path, tmp_path: Path
) -> None:
    """``posediff eval``'s scores and ``posediff score`` of the CSV it wrote are the same numbers."""
    import json

    from posediff.cli import main

    res = evaluate_bop(Oracle(dm, shift_mm=12.0), dm, num_samples=3)
    path = write_bop19_csv(tmp_path / "posediff_fixture-test.csv", res["estimates"])
    assert all(e.score == 1.0 for e in read_bop19_csv(path))  # three equal hypotheses: one mode, weight 1
    run = tmp_path / "score"
    assert main(["score", f"csv={path}", f"data.root={bop_root}", f"hydra.run.dir={run}"]) == 0
    scored = json.loads((run / "metrics.json").read_text())
    assert (run / "metrics.md").read_text().startswith(str(path))
    for row in ("overall", "object_mean"):
        for key, value in res[row].items():
            assert scored[row][key] == pytest.approx(value, abs=1e-12, nan_ok=True), (row, key)
    assert scored["shapes"].keys() == res["shapes"].keys()
    for obj, row in res["shapes"].items():
        assert scored["shapes"][obj] == pytest.approx(row, abs=1e-12, nan_ok=True), obj
    assert 0.0 < res["overall"]["AR"] < 1.0 and res["overall"]["recall_trans@2cm"] > 0.5
    assert scored["matching"] == "bop19" and scored["estimates_ignored"] == 0


def test_several_hypotheses_give_the_heaviest_mode_and_its_weight() -> None:
    from posediff.evaluation.bop import best_hypothesis
    from posediff.lie import SO3

    g = torch.Generator().manual_seed(0)
    A, B = SO3().exp(torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)), torch.eye(3, dtype=torch.float64)
    jitter = SO3().exp(0.01 * torch.randn(10, 3, generator=g, dtype=torch.float64))
    R = torch.cat([A @ jitter[:7], B @ jitter[7:]])
    t = (
        torch.cat([torch.full((7, 3), 100.0), torch.full((3, 3), 100.0)]).double()
        + torch.randn(10, 3, generator=g).double()
    )
    Rb, tb, score = best_hypothesis(R, t)
    assert score == pytest.approx(0.7)
    assert np.degrees(np.arccos(np.clip((np.trace(Rb @ A.numpy().T) - 1) / 2, -1, 1))) < 1.0
    assert np.abs(tb - 100.0).max() < 2.0
    R1, t1, s1 = best_hypothesis(R[:1], t[:1])  # one hypothesis: itself, score 1
    assert s1 == 1.0 and np.array_equal(R1, R[0].numpy()) and np.array_equal(t1, t[0].numpy())
