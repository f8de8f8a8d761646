"""BOP19 matching on the fixture's sibling instances (several instances of one object in one image):
``score_estimates`` (shared by ``posediff eval`` and ``posediff score``) against hand-computed recalls."""

from pathlib import Path

import numpy as np
import pytest

from posediff.data.bop import BopDataModule
from posediff.evaluation.bop import check_estimates, score_estimates
from posediff.metrics.bop19 import BopEstimate

PAPER = ("recall_rot@2", "recall_rot@10", "recall_trans@2cm", "recall_x@2cm", "recall_z@10cm")
BOP = ("AR_MSSD", "AR_MSPD", "AR_VSD", "AR")


@pytest.fixture(scope="module")
def dm(bop_root: Path) -> BopDataModule:
    d = BopDataModule(str(bop_root), image_size=32, num_workers=0, augment=None)
    d.read_targets()  # the test ground truth only: no dataset, no translation statistics
    return d


def _groups(dm: BopDataModule) -> dict[tuple[int, int, int], list]:
    out: dict[tuple[int, int, int], list] = {}
    for inst in dm.targets:
        out.setdefault((inst.scene_id, inst.im_id, inst.obj_id), []).append(inst)
    return out


def _est(inst, R=None, t=None, score: float = 1.0) -> BopEstimate:  # noqa: ANN001
    return BopEstimate(inst.scene_id, inst.im_id, inst.obj_id, score,
                       inst.R if R is None else R, inst.t if t is None else t, 0.5)  # fmt: skip


def _siblings(dm: BopDataModule) -> list[list]:
    groups = [g for g in _groups(dm).values() if len(g) >= 2]
    assert groups, "the fixture must hold images with several instances of one object"
    return groups


def test_the_fixture_has_sibling_targets(dm: BopDataModule) -> None:
    groups = _siblings(dm)
    assert sum(len(g) for g in groups) >= 6
    # and they are genuinely different poses (else swapping them would prove nothing)
    for g in groups:
        t = np.stack([i.t for i in g])
        assert np.linalg.norm(t[:, None] - t[None], axis=-1)[np.triu_indices(len(g), 1)].min() > 20.0


def test_perfect_estimates_score_one(dm: BopDataModule) -> None:
    res = score_estimates(dm, [_est(i) for i in dm.targets])
    for key in (*BOP, *PAPER):
        assert res["overall"][key] == pytest.approx(1.0), key
    assert res["estimates_scored"] == len(dm.targets) and res["estimates_ignored"] == 0


def test_estimates_swapped_between_siblings_score_one(dm: BopDataModule) -> None:
    """Each sibling's estimate is another sibling's exact pose (a cyclic shift within the image and
    object): the toolkit matches every estimate to the sibling it equals — AR 1.0 (the old paired
    scoring gave 0.235 on such a case)."""
    rows = []
    for g in _groups(dm).values():
        for k, inst in enumerate(g):
            other = g[(k + 1) % len(g)]
            rows.append(_est(inst, other.R, other.t))
    res = score_estimates(dm, rows)
    for key in (*BOP, *PAPER):
        assert res["overall"][key] == pytest.approx(1.0), key
    for row in res["shapes"].values():
        assert row["AR"] == pytest.approx(1.0)


def test_duplicates_of_one_pose_match_once(dm: BopDataModule) -> None:
    """All inst_count estimates of a sibling group are the first sibling's pose. The first copy matches
    that sibling (error 0); a further copy can only match a sibling whose error to that pose is below
    the threshold — hand-computed per threshold from the pairwise errors: matches = 1 + #{j > 0: e_j < θ}.
    Where no sibling is that near (MSSD, T@2cm: siblings are > 20 mm apart), exactly one match."""
    from posediff.metrics import bop

    rows, lost = [], 0
    hand = {"AR_MSSD": 0.0, "AR_MSPD": 0.0}
    n = len(dm.targets)
    k_mssd = np.arange(1, 11) * 0.05
    for g in _groups(dm).values():
        rows += [_est(inst, g[0].R, g[0].t) for inst in g]
        lost += len(g) - 1
        o = g[0].obj_id
        pts, syms = dm.models.points(o), dm.models.symmetries(o, evaluation=True)
        diam = dm.models.diameter(o, evaluation=True)
        mssd = np.array([bop.mssd(g[0].R, g[0].t, j.R, j.t, pts, syms, diameter=diam) for j in g[1:]])
        mspd = np.array([bop.mspd(g[0].R, g[0].t, j.R, j.t, j.K, pts, syms) for j in g[1:]])
        k_mspd = np.arange(1, 11) * 5.0 * g[0].image_hw[1] / 640.0
        hand["AR_MSSD"] += np.mean([1 + np.sum(mssd < k * diam) for k in k_mssd])
        hand["AR_MSPD"] += np.mean([1 + np.sum(mspd < k) for k in k_mspd])
    assert lost >= 3
    res = score_estimates(dm, rows, vsd=False)
    for key, matched in hand.items():
        assert res["overall"][key] == pytest.approx(matched / n), key
    assert res["overall"]["AR_MSSD"] == pytest.approx((n - lost) / n)  # siblings are far apart in MSSD
    assert res["overall"]["recall_trans@2cm"] == pytest.approx((n - lost) / n)
    assert res["estimates_scored"] == n


def test_only_the_top_inst_count_estimates_by_score_count(dm: BopDataModule) -> None:
    """A group of G siblings gets G exact estimates and one far-off one. Scored highest, the far-off
    one takes a place among the top G and one sibling is missed; scored lowest, it is ignored."""
    groups = _siblings(dm)
    far = np.array([900.0, 900.0, 5000.0])
    n = len(dm.targets)
    for junk_score, missed in ((2.0, len(groups)), (0.1, 0)):
        rows = [_est(i) for i in dm.targets]
        rows += [_est(g[0], g[0].R, far, score=junk_score) for g in groups]
        res = score_estimates(dm, rows, vsd=False)
        for key in ("AR_MSSD", "AR_MSPD", "recall_trans@2cm", "recall_x@2cm"):
            assert res["overall"][key] == pytest.approx((n - missed) / n), (junk_score, key)
        assert res["estimates_ignored"] == len(groups)
        assert np.isnan(res["overall"]["AR_VSD"]) and np.isnan(res["overall"]["AR"])


def test_hand_computed_mssd_recalls_of_shifted_estimates(dm: BopDataModule) -> None:
    """Estimate k of every target shifted along the camera x axis by d_k mm: its MSSD to its own
    instance is d_k (a translation moves every point by d_k; the identity is a symmetry), to every
    sibling it is larger (checked), so at threshold τ·diameter the recall is #{k: d_k < τ·diameter} / n;
    MSPD / T@ / x@ likewise from the same shifts."""
    from posediff.metrics import bop

    shifts = (0.0, 3.0, 12.0, 30.0, 55.0, 140.0)
    rows, d_of = [], []
    for k, inst in enumerate(dm.targets):
        d = shifts[k % len(shifts)]
        rows.append(_est(inst, inst.R, inst.t + [d, 0.0, 0.0]))
        d_of.append((inst, d))
    for (inst, d), row in zip(d_of, rows, strict=True):  # the premise: the own instance is the nearest
        for other in dm.targets:
            if other is not inst and other.key[:2] == inst.key[:2] and other.obj_id == inst.obj_id:
                diam = dm.models.diameter(inst.obj_id, evaluation=True)
                e = bop.mssd(row.R, row.t, other.R, other.t, dm.models.points(inst.obj_id),
                             dm.models.symmetries(inst.obj_id, evaluation=True), diameter=diam)  # fmt: skip
                assert e > 0.5 * diam or e > d + 1.0
    res = score_estimates(dm, rows, vsd=False)
    n = len(rows)
    taus = np.arange(1, 11) * 0.05
    hand = np.mean(
        [[d < tau * dm.models.diameter(i.obj_id, evaluation=True) for tau in taus] for i, d in d_of], axis=0
    )
    assert res["overall"]["AR_MSSD"] == pytest.approx(float(hand.mean()))
    assert res["overall"]["recall_trans@2cm"] == pytest.approx(sum(d < 20.0 for _, d in d_of) / n)
    assert res["overall"]["recall_x@5cm"] == pytest.approx(sum(d < 50.0 for _, d in d_of) / n)
    assert res["overall"]["recall_z@2cm"] == pytest.approx(1.0)  # z untouched
    assert res["overall"]["recall_rot@2"] == pytest.approx(1.0)


def test_rows_of_unknown_objects_and_images_are_refused(dm: BopDataModule) -> None:
    inst = dm.targets[0]
    check_estimates([_est(inst)], dm)
    bad_obj = BopEstimate(inst.scene_id, inst.im_id, 77, 1.0, inst.R, inst.t, 0.5)
    with pytest.raises(
        ValueError, match=r"row 2: obj_id 77 is not in .*models_info.json \(objects 1, 2, 3\)"
    ):
        check_estimates([_est(inst), bad_obj], dm)
    bad_im = BopEstimate(inst.scene_id, 999, inst.obj_id, 1.0, inst.R, inst.t, 0.5)
    with pytest.raises(ValueError, match="x.csv:7: scene 1 image 999 holds no target"):
        check_estimates([bad_im], dm, where=["x.csv:7"])
    # an object that is no target of the image is ignored, as the toolkit ignores it
    absent = [o for o in (1, 2, 3) if (inst.scene_id, inst.im_id, o) not in dm.inst_count]
    if absent:
        extra = BopEstimate(inst.scene_id, inst.im_id, absent[0], 1.0, inst.R, inst.t, 0.5)
        res = score_estimates(dm, [_est(i) for i in dm.targets] + [extra], vsd=False)
        assert res["estimates_ignored"] == 1 and res["overall"]["AR_MSSD"] == pytest.approx(1.0)
