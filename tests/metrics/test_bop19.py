"""BOP19 protocol: thresholds, matching, average recall, the paper's pose recalls and the results CSV,
on hand-made cases whose answers follow from the definitions."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from posediff.metrics.bop import symmetry_transforms
from posediff.metrics.bop19 import (
    BOP19,
    CSV_HEADER,
    BopEstimate,
    ImageObjectErrors,
    ar_from_paired_errors,
    average_recall,
    match,
    mspd_correct,
    mssd_correct,
    pose_recalls,
    read_bop19_csv,
    symmetric_rotation_errors_deg,
    vsd_correct,
    write_bop19_csv,
)

#: T-LESS objects 1 and 5 as published in BOP's models_info.json (diameter mm, box, symmetries; CC BY 4.0,
#: Hodaň et al. 2017), carried in the tests so that they run everywhere
TLESS = Path(__file__).with_name("tless_models_info_obj1_obj5.json")
NAN = math.nan


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


# --------------------------------------------------------------------------------------------------
# Thresholds and strictness
# --------------------------------------------------------------------------------------------------


def test_thresholds() -> None:
    tenths = [0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5]
    assert list(BOP19.vsd_taus) == tenths and list(BOP19.vsd_thetas) == tenths
    assert list(BOP19.mssd_thresholds) == tenths
    assert list(BOP19.mspd_thresholds) == [5.0 * k for k in range(1, 11)]
    assert BOP19.vsd_delta == 15.0 and BOP19.visib_gt_min == 0.1
    np.testing.assert_allclose(BOP19.mspd_thresholds_px(640), BOP19.mspd_thresholds)
    assert BOP19.mspd_thresholds_px(720)[0] == 5.625  # 5 · 720 / 640


def test_error_exactly_at_threshold_is_not_correct() -> None:
    # MSSD 25 mm of a 100 mm object = 0.25 · d: correct only for k > 0.25, i.e. 0.30 … 0.50
    np.testing.assert_array_equal(mssd_correct(25.0, 100.0), [False] * 5 + [True] * 5)
    np.testing.assert_array_equal(mssd_correct(5.0, 100.0)[:2], [False, True])
    # MSPD 10 px at width 640: correct for k = 15 … 50
    np.testing.assert_array_equal(mspd_correct(10.0, 640), [False, False] + [True] * 8)
    # VSD 0.3 at every τ: correct for θ = 0.35 … 0.5
    ok = vsd_correct(np.full(10, 0.3))
    assert ok.shape == (10, 10) and (ok == ([False] * 6 + [True] * 4)).all()
    # NaN (no estimate) is never correct
    assert not mssd_correct(NAN, 100.0).any() and not mspd_correct(NAN, 640).any()


def test_mspd_threshold_scales_with_image_width() -> None:
    """Width 720: the first threshold is 5 · 720/640 = 5.625 px (the toolkit compares e · 640/w < 5)."""
    assert mspd_correct(5.6, 720)[0]
    assert not mspd_correct(5.625, 720)[0]  # 5.625 · 640/720 = 5 exactly → not < 5
    assert not mspd_correct(5.6, 640)[0]
    assert mspd_correct(5.6, 1280)[0] and not mspd_correct(5.0, 320)[1]  # 5 · 640/320 = 10, not < 10
    res = ar_from_paired_errors(None, None, [5.6, 5.6], None, [720, 640])
    assert res["recall_mspd"][0] == 0.5 and res["recall_mspd"][1] == 1.0


# --------------------------------------------------------------------------------------------------
# Matching
# --------------------------------------------------------------------------------------------------


def test_match_two_instances_three_estimates() -> None:
    """Errors in mm, threshold 10. In score order: est 1 (0.9) hits nothing; est 2 (0.8) is closest to
    GT 0; est 0 (0.5) is only considered without the top-inst_count rule, then takes GT 1."""
    scores = [0.5, 0.9, 0.8]
    errors = [[1.0, 1.0], [50.0, 50.0], [2.0, 20.0]]
    top2 = match(scores, errors, [10.0], max_estimates=2)
    np.testing.assert_array_equal(top2.gt_matched, [[True, False]])
    np.testing.assert_array_equal(top2.est_to_gt, [[-1, -1, 0]])
    everything = match(scores, errors, [10.0])
    np.testing.assert_array_equal(everything.gt_matched, [[True, True]])
    np.testing.assert_array_equal(everything.est_to_gt, [[1, -1, 0]])
    # per threshold: at 1.5 only est 0 is close enough (to both; the first GT wins the tie)
    per = match(scores, errors, [1.5, 10.0])
    np.testing.assert_array_equal(per.gt_matched, [[True, False], [True, True]])
    np.testing.assert_array_equal(per.est_to_gt[0], [0, -1, -1])


def test_match_swapped_assignment() -> None:
    """Estimate A (made for GT 0) lies closer to GT 1, and has the higher score: it takes GT 1 and the
    other estimate falls back to GT 0 — both GTs are found although the pairs are swapped."""
    errors = [[4.0, 1.0], [2.0, 3.0]]
    m = match([0.9, 0.8], errors, [5.0])
    np.testing.assert_array_equal(m.est_to_gt, [[1, 0]])
    # with a tighter threshold the second estimate's fallback (2.0) is still below, the first's too
    np.testing.assert_array_equal(match([0.9, 0.8], errors, [2.5]).gt_matched, [[True, True]])
    # at 1.5 estimate B has no GT left below the threshold
    np.testing.assert_array_equal(match([0.9, 0.8], errors, [1.5]).est_to_gt, [[1, -1]])
    # strict: an error equal to the threshold does not match
    assert not match([1.0], [[5.0]], [5.0]).gt_matched.any()


def test_match_ignores_invalid_gt_and_nan() -> None:
    m = match([0.9], [[3.0, 1.0]], [5.0], gt_valid=[True, False])
    np.testing.assert_array_equal(m.est_to_gt, [[0]])  # falls back to the valid GT
    m = match([0.9], [[NAN, 1.0]], [5.0], gt_valid=[True, False])
    assert (m.est_to_gt == -1).all()
    # VSD-shaped: (E, G, n_τ, 1) errors against θ (n_θ,)
    v = np.full((1, 1, 10, 1), 0.3)
    assert match([1.0], v, np.asarray(BOP19.vsd_thetas)).gt_matched.shape == (10, 10, 1)


# --------------------------------------------------------------------------------------------------
# Average recall
# --------------------------------------------------------------------------------------------------


def _paired(n_good: int, n_missing: int) -> dict:
    n = n_good + n_missing
    vsd = np.zeros((n, 10))
    mssd, mspd = np.zeros(n), np.zeros(n)
    vsd[n_good:], mssd[n_good:], mspd[n_good:] = NAN, NAN, NAN
    return {"vsd": vsd, "mssd": mssd, "mspd": mspd, "diameters": np.full(n, 100.0), "image_width": 640}


def test_ar_perfect_none_and_half() -> None:
    perfect = ar_from_paired_errors(**_paired(3, 0))
    assert perfect["AR"] == perfect["AR_VSD"] == perfect["AR_MSSD"] == perfect["AR_MSPD"] == 1.0
    assert perfect["recall_vsd"].shape == (10, 10) and perfect["n_targets"] == 3
    none = ar_from_paired_errors(**_paired(0, 3))
    assert none["AR"] == 0.0 and not none["recall_mssd"].any()
    half = ar_from_paired_errors(**_paired(2, 2))
    assert half["AR"] == half["AR_VSD"] == half["AR_MSSD"] == half["AR_MSPD"] == 0.5
    # constructed: every MSSD 0.25·d (correct for 5 of 10 k), every MSPD 25 px (correct for k = 30 … 50),
    # every VSD 0.3 (correct for 4 of 10 θ): AR = (0.4 + 0.5 + 0.3) / 3
    res = ar_from_paired_errors(np.full((4, 10), 0.3), np.full(4, 25.0), np.full(4, 25.0), 100.0, 640)
    assert (
        res["AR_VSD"] == pytest.approx(0.4) and res["AR_MSSD"] == 0.5 and res["AR_MSPD"] == pytest.approx(0.5)
    )
    res = ar_from_paired_errors(np.full((4, 10), 0.3), np.full(4, 25.0), np.full(4, 30.0), 100.0, 640)
    assert res["AR_MSPD"] == pytest.approx(0.4) and res["AR"] == pytest.approx((0.4 + 0.5 + 0.4) / 3)
    only = ar_from_paired_errors(None, np.zeros(2), None, 100.0, 640)
    assert only["AR_MSSD"] == 1.0 and math.isnan(only["AR_VSD"]) and math.isnan(only["AR"])


def test_low_visibility_target_is_ignored() -> None:
    p = _paired(1, 1)  # the second target has no estimate …
    res = ar_from_paired_errors(**p, visib_fract=[0.5, 0.05])  # … but is only 5 % visible
    assert res["AR"] == 1.0 and res["n_targets"] == 1
    assert ar_from_paired_errors(**p, visib_fract=[0.5, 0.1])["AR"] == 0.5  # 0.1 itself counts
    # full matrices: one estimate lying on the hidden instance is neither a hit nor counted
    g = ImageObjectErrors(
        obj_id=5,
        diameter=100.0,
        image_width=640,
        scores=[1.0],
        visib_fract=[0.5, 0.05],
        mssd=[[80.0, 0.0]],
        mspd=[[80.0, 0.0]],
        vsd=np.stack([np.full(10, 0.9), np.zeros(10)])[None],
    )
    res = average_recall([g])
    assert res["n_targets"] == 1 and res["AR"] == 0.0
    g.mssd, g.mspd = [[0.0, 0.0]], [[0.0, 0.0]]
    g.vsd = np.zeros((1, 2, 10))
    assert average_recall([g])["AR"] == 1.0


def test_average_recall_groups_and_per_object() -> None:
    """Image 1: two instances of object 1, three estimates (top-2 rule drops the best one, the
    high-scored bad one finds nothing): 1 of 2. Image 2: one instance of object 5, matched. Pooled:
    2 of 3 targets, not the mean of the per-object recalls (½ and 1)."""
    bad, good = 1e3, 0.0
    g1 = ImageObjectErrors(
        obj_id=1,
        diameter=100.0,
        image_width=640,
        scores=[0.5, 0.9, 0.8],
        visib_fract=[0.9, 0.8],
        mssd=[[good, good], [bad, bad], [good, bad]],
        mspd=[[good, good], [bad, bad], [good, bad]],
        vsd=np.array([[0, 0], [1, 1], [0, 1]], float)[:, :, None].repeat(10, axis=2),
    )
    g2 = ImageObjectErrors(
        obj_id=5,
        diameter=50.0,
        image_width=640,
        scores=[0.3],
        visib_fract=[1.0],
        mssd=[[1.0]],
        mspd=[[1.0]],
        vsd=np.zeros((1, 1, 10)),
        im_id=2,
    )
    res = average_recall([g1, g2])
    assert res["n_targets"] == 3 and res["AR"] == pytest.approx(2 / 3)
    assert res["per_object"][1]["AR"] == 0.5 and res["per_object"][5]["AR"] == 1.0
    assert res["AR_obj_mean"] == pytest.approx(0.75)
    g1.inst_count = 3  # all three estimates considered: the 0.5-scored one takes the remaining GT
    assert average_recall([g1, g2])["AR"] == 1.0
    # paired errors give the same as one-estimate-one-GT groups
    paired = ar_from_paired_errors(
        np.zeros((3, 10)), [0.0, NAN, 1.0], [0.0, NAN, 1.0], [100.0, 100.0, 50.0], 640, obj_ids=[1, 1, 5]
    )
    np.testing.assert_array_equal(paired["recall_vsd"][:, 0], [1.0] * 10)
    assert paired["AR_MSSD"] == pytest.approx(2 / 3) and paired["per_object"][1]["AR_MSSD"] == 0.5
    assert paired["per_object"][5]["n_targets"] == 1
    empty = average_recall([])
    assert empty["AR"] == 0.0 and empty["n_targets"] == 0


# --------------------------------------------------------------------------------------------------
# The paper's pose recalls
# --------------------------------------------------------------------------------------------------


def test_pose_recalls_symmetry_and_shift() -> None:
    """Target 0: off by the Rz(π) symmetry; target 1: exact rotation, 3 cm shift along x."""
    syms = symmetry_transforms(
        {"symmetries_discrete": [np.block([[rz(math.pi), np.zeros((3, 1))], [np.zeros((1, 3)), 1]]).ravel()]}
    )
    R_gt = np.stack([rx(0.4) @ rz(0.3)] * 2)
    t_gt = np.array([[10.0, -20.0, 700.0], [0.0, 0.0, 900.0]])
    R_est = np.stack([R_gt[0] @ rz(math.pi), R_gt[1]])
    t_est = t_gt + [[0.0, 0, 0], [30.0, 0, 0]]
    rec = pose_recalls(R_est[:1], t_est[:1], R_gt[:1], t_gt[:1], syms)
    assert rec["R@2"] == 1.0 and rec["T@2cm"] == 1.0
    assert pose_recalls(R_est[:1], t_est[:1], R_gt[:1], t_gt[:1])["R@10"] == 0.0  # no symmetry given
    rec = pose_recalls(R_est[1:], t_est[1:], R_gt[1:], t_gt[1:], syms)
    assert rec["R@2"] == 1.0
    assert rec["T@2cm"] == 0.0 and rec["T@5cm"] == 1.0 and rec["T@10cm"] == 1.0
    assert rec["x@2cm"] == 0.0 and rec["x@5cm"] == 1.0 and rec["y@2cm"] == 1.0 and rec["z@2cm"] == 1.0
    both = pose_recalls(R_est, t_est, R_gt, t_gt, [syms, syms])
    assert both["R@2"] == 1.0 and both["T@2cm"] == 0.5 and both["x@2cm"] == 0.5
    assert set(both) == {f"{k}@{v}" for k in "R" for v in (2, 5, 10)} | {
        f"{k}@{v}cm" for k in "Txyz" for v in (2, 5, 10)
    }
    # strict at the threshold (20 mm), and a missing estimate is a miss
    rec = pose_recalls(
        np.stack([np.eye(3)] * 2), [[0, 0, 20.0], [NAN] * 3], np.stack([np.eye(3)] * 2), [[0, 0, 0.0]] * 2
    )
    assert rec["T@2cm"] == 0.0 and rec["z@2cm"] == 0.0 and rec["T@5cm"] == 0.5 and rec["x@2cm"] == 0.5
    # per-target sets: only the second target is symmetric
    errs = symmetric_rotation_errors_deg(np.stack([rz(math.pi)] * 2), np.stack([np.eye(3)] * 2), [None, syms])
    np.testing.assert_allclose(errs, [180.0, 0.0], atol=1e-6)


def test_pose_recalls_real_tless_symmetries() -> None:
    """T-LESS obj 1 (continuous about z): any rotation about z is within half a step (0.29°) of the
    discretised set; obj 5 (Rz(π)): the flip is free, a 3° tilt is not."""
    info = json.loads(TLESS.read_text())
    s1, s5 = symmetry_transforms(info["1"]), symmetry_transforms(info["5"])
    R_gt = np.stack([rx(0.2)] * 3)
    R_est = np.stack(
        [rx(0.2) @ rz(0.777), rx(0.2) @ rz(math.pi), rx(0.2) @ rz(math.pi) @ rx(math.radians(3))]
    )
    errs = symmetric_rotation_errors_deg(R_est, R_gt, [s1, s5, s5])
    assert errs[0] < 0.5 * 360 / len(s1[0]) + 1e-9 and errs[1] < 1e-5 and errs[2] == pytest.approx(3.0)
    rec = pose_recalls(R_est, np.zeros((3, 3)), R_gt, np.zeros((3, 3)), [s1, s5, s5])
    assert rec["R@2"] == pytest.approx(2 / 3) and rec["R@5"] == 1.0


# --------------------------------------------------------------------------------------------------
# Results CSV
# --------------------------------------------------------------------------------------------------


def test_csv_round_trip(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    rows = [
        BopEstimate(1, 3, 5, 0.9, rx(0.3) @ rz(1.1), np.array([12.5, -3.25, 700.125]), 0.25),
        {
            "scene_id": 1,
            "im_id": 3,
            "obj_id": 1,
            "score": 0.1,
            "R": torch.eye(3),
            "t": [0, 0, 1e-5],
            "time": 0.25,
        },
        {"scene_id": 2, "im_id": 0, "obj_id": 1, "score": 1.0, "R": np.eye(3), "t": np.zeros((3, 1))},
    ]
    path = write_bop19_csv(tmp_path / "res" / "method_tless-test.csv", rows)
    lines = path.read_text().splitlines()
    assert lines[0] == CSV_HEADER and len(lines) == 4
    assert lines[3] == "2,0,1,1.0,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,0.0 0.0 0.0,-1.0"
    back = read_bop19_csv(path)
    assert back[0] == rows[0]  # exact: shortest round-trip floats
    assert back[1].obj_id == 1 and back[1].t[2] == 1e-5 and back[2].time == -1.0
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    with pytest.raises(ValueError, match="one time per image"):
        write_bop19_csv(tmp_path / "bad.csv", [rows[0], {**rows[1], "time": 0.5}])
    assert not (tmp_path / "bad.csv").exists()


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1,3,5,0.9,1 0 0 0 1 0 0 0 1,0 0 1", "6 comma-separated fields"),
        ("1,3,5,0.9,1 0 0 0 1 0 0 0,0 0 1,0.1", "R has 8 numbers"),
        ("1,3,5,high,1 0 0 0 1 0 0 0 1,0 0 1,0.1", "could not convert"),
        ("1,3,5.5,0.9,1 0 0 0 1 0 0 0 1,0 0 1,0.1", "invalid literal"),
        ("1,3,5,0.9,1 0 0 0 1 0 0 0 1,0 0 1,0.7", "one time per image"),
    ],
)
def test_malformed_csv(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "r.csv"
    path.write_text(f"{CSV_HEADER}\n1,3,2,0.5,1 0 0 0 1 0 0 0 1,0 0 1,0.1\n{line}\n")
    with pytest.raises(ValueError, match=message) as info:
        read_bop19_csv(path)
    assert str(info.value).startswith(f"{path}:3: ") and "\n" not in str(info.value)
    path.write_text("scene_id,im_id,obj_id,score,R,t\n")
    with pytest.raises(ValueError, match=r"r\.csv:1: header"):
        read_bop19_csv(path)


def test_pose_recalls_use_the_symmetries_translations() -> None:
    """An object whose origin is 50 mm off its symmetry axis: the pose ``P · S`` with ``S`` a half
    turn about that axis moves the origin by 100 mm, yet it is the same pose (the authors' teS)."""
    from posediff.metrics.bop import symmetry_transforms
    from posediff.metrics.bop19 import pose_recalls

    S = np.eye(4)
    S[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    S[:3, 3] = [100.0, 0.0, 0.0]  # Rz(π) about the axis through (50, 0, 0)
    syms = symmetry_transforms({"diameter": 120.0, "symmetries_discrete": [S.reshape(-1).tolist()]})
    c, s = np.cos(0.3), np.sin(0.3)
    R_gt = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t_gt = np.array([10.0, -20.0, 700.0])
    R_est, t_est = R_gt @ S[:3, :3], t_gt + R_gt @ S[:3, 3]
    rec = pose_recalls(R_est[None], t_est[None], R_gt[None], t_gt[None], syms)
    assert rec["R@2"] == 1.0 and rec["T@2cm"] == 1.0 and rec["x@2cm"] == 1.0
    plain = pose_recalls(R_est[None], t_est[None], R_gt[None], t_gt[None], (syms[0], np.zeros_like(syms[1])))
    assert plain["T@2cm"] == 0.0 and plain["T@5cm"] == 0.0  # 100 mm apart without the offset
