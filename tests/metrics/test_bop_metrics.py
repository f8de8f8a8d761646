"""BOP pose errors on hand-made cases whose answers follow from the definitions."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from posediff.metrics.bop import (
    add,
    adi,
    depth_to_distance,
    mspd,
    mssd,
    re,
    sphere_projections_overlap,
    symmetry_transforms,
    te,
    vsd,
)

#: T-LESS objects 1 and 5 as published in BOP's models_info.json (diameter mm, box, symmetries; CC BY 4.0,
#: Hodaň et al. 2017), carried in the tests so that they run everywhere
TLESS = Path(__file__).with_name("tless_models_info_obj1_obj5.json")
BOX = np.array([[x, y, z] for x in (-2.0, 2.0) for y in (-1.0, 1.0) for z in (-0.5, 0.5)])  # 4×2×1 box
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_symmetry_sets() -> None:
    R, t = symmetry_transforms({})
    assert R.shape == (1, 3, 3) and np.allclose(R[0], np.eye(3)) and np.allclose(t, 0)
    disc = {
        "symmetries_discrete": [np.block([[rz(math.pi), np.zeros((3, 1))], [np.zeros((1, 3)), 1]]).ravel()]
    }
    R, t = symmetry_transforms(disc)
    assert R.shape == (2, 3, 3) and np.allclose(R[0], np.eye(3)) and np.allclose(R[1], rz(math.pi))
    cont = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [1.0, 0, 0]}]}
    R, t = symmetry_transforms(cont, max_sym_disc_step=0.1)
    n = math.ceil(math.pi / 0.1)
    assert R.shape == (n, 3, 3) and np.allclose(R[0], np.eye(3))
    # a rotation about the axis through the offset keeps the offset point fixed
    for Rk, tk in zip(R, t, strict=True):
        assert np.allclose(Rk @ np.array([1.0, 0, 0]) + tk, [1.0, 0, 0])
    both = {**disc, **cont}
    assert len(symmetry_transforms(both, 0.1)[0]) == 2 * n
    with pytest.raises(ValueError, match="not 16"):
        symmetry_transforms({"symmetries_discrete": [[1, 0, 0]]})


def test_real_tless_models_info() -> None:
    info = json.loads(TLESS.read_text())
    assert (info["1"]["diameter"], info["5"]["diameter"]) == (63.5151, 108.69)
    R1, _ = symmetry_transforms(info["1"], max_sym_disc_step=0.01)
    assert len(R1) == math.ceil(math.pi / 0.01)
    R5, t5 = symmetry_transforms(info["5"])
    assert len(R5) == 2 and np.allclose(R5[1], rz(math.pi), atol=1e-12) and np.allclose(t5, 0)


def test_errors_of_a_symmetric_pose_vanish() -> None:
    """The box is symmetric under Rz(π): an estimate off by exactly that has MSSD = MSPD = 0,
    while ADD (no symmetry) sees the full flip."""
    syms = symmetry_transforms(
        {"symmetries_discrete": [np.block([[rz(math.pi), np.zeros((3, 1))], [np.zeros((1, 3)), 1]]).ravel()]}
    )
    R_gt, t_gt = rz(0.3), np.array([0.1, -0.2, 20.0])
    R_est = R_gt @ rz(math.pi)
    assert mssd(R_est, t_gt, R_gt, t_gt, BOX, syms) == pytest.approx(0.0, abs=1e-9)
    assert mspd(R_est, t_gt, R_gt, t_gt, K, BOX, syms) == pytest.approx(0.0, abs=1e-7)
    assert add(R_est, t_gt, R_gt, t_gt, BOX) == pytest.approx(2 * math.hypot(2.0, 1.0))
    assert adi(R_est, t_gt, R_gt, t_gt, BOX) == pytest.approx(0.0, abs=1e-9)
    assert re(R_est, R_gt) == pytest.approx(180.0)
    # without the symmetry annotation MSSD is the farthest corner's displacement
    none = symmetry_transforms({})
    assert mssd(R_est, t_gt, R_gt, t_gt, BOX, none) == pytest.approx(2 * math.hypot(2.0, 1.0))


def test_known_shift() -> None:
    syms = symmetry_transforms({})
    R, t = np.eye(3), np.array([0.0, 0.0, 10.0])
    shift = np.array([0.3, -0.4, 0.0])  # |shift| = 0.5 in the image plane
    assert mssd(R, t + shift, R, t, BOX, syms) == pytest.approx(0.5)
    assert add(R, t + shift, R, t, BOX) == pytest.approx(0.5)
    assert te(t + shift, t) == pytest.approx(0.5)
    assert re(R, R) == pytest.approx(0.0)
    # every point moves by f·|shift|/z in the image: MSPD is the largest, for the nearest points (z = 9.5)
    assert mspd(R, t + shift, R, t, K, BOX, syms) == pytest.approx(500 * 0.5 / 9.5)


def test_vsd_hand_cases() -> None:
    """VSD on depth maps: equal maps → 0; no estimate → 1; a fronto-parallel plate moved back by
    d → error 0 for τ > d/diameter and 1 for τ ≤ d/diameter; a half-covering estimate → ½."""
    Kc = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    plate = np.zeros((64, 64))
    plate[16:48, 16:48] = 1000.0  # a square plate at 1000 mm
    taus = [0.05, 0.1, 0.2]
    assert vsd(plate, plate, plate, Kc, 15.0, taus, diameter=100.0) == [0.0, 0.0, 0.0]
    assert vsd(np.zeros_like(plate), plate, plate, Kc, 15.0, taus, diameter=100.0) == [1.0, 1.0, 1.0]
    assert vsd(np.zeros_like(plate), np.zeros_like(plate), plate, Kc, 15.0, taus, 100.0) == [1.0, 1.0, 1.0]
    # the estimate 10 mm behind, test depth 0 (no measurement, so everything is visible): distances differ
    # by 10·(ray length / depth) ≥ 10 mm = 0.1 diameters
    back = np.where(plate > 0, 1010.0, 0.0)
    errs = vsd(back, plate, np.zeros_like(plate), Kc, 15.0, taus, diameter=100.0)
    assert errs == [1.0, 1.0, 0.0]
    half = plate.copy()
    half[16:48, 32:48] = 0.0  # the estimate covers half of the ground truth's pixels
    assert vsd(half, plate, plate, Kc, 15.0, taus, diameter=100.0) == [0.5, 0.5, 0.5]
    with pytest.raises(ValueError, match="available: step"):
        vsd(plate, plate, plate, Kc, 15.0, taus, 100.0, cost="tlinear")


# --------------------------------------------------------------------------------------------------
# Batches, torch inputs and the toolkit's short-cuts
# --------------------------------------------------------------------------------------------------


def _rand_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)


def _batch(n: int = 5, seed: int = 0):  # noqa: ANN202 - R_est, t_est, R_gt, t_gt
    rng = np.random.default_rng(seed)
    t_gt = rng.normal(size=(n, 3)) * 2 + [0.0, 0.0, 30.0]
    return _rand_rotations(n, rng), t_gt + rng.normal(size=(n, 3)), _rand_rotations(n, rng), t_gt


SYMS_MIXED = symmetry_transforms(
    {
        "symmetries_discrete": [np.block([[rz(math.pi), np.zeros((3, 1))], [np.zeros((1, 3)), 1]]).ravel()],
        "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0.5, 0, 0]}],
    },
    max_sym_disc_step=0.2,
)


def test_batched_equals_loop_of_single_pairs() -> None:
    R_e, t_e, R_g, t_g = _batch()
    pts = np.random.default_rng(1).normal(size=(300, 3))
    cases = {
        "mssd": (lambda *a: mssd(*a, pts, SYMS_MIXED), (R_e, t_e, R_g, t_g)),
        "mspd": (lambda *a: mspd(*a, K, pts, SYMS_MIXED), (R_e, t_e, R_g, t_g)),
        "add": (lambda *a: add(*a, pts), (R_e, t_e, R_g, t_g)),
        "adi": (lambda *a: adi(*a, pts), (R_e, t_e, R_g, t_g)),
        "re": (re, (R_e, R_g)),
        "te": (te, (t_e, t_g)),
    }
    for name, (f, args) in cases.items():
        batched = f(*args)
        assert isinstance(batched, np.ndarray) and batched.shape == (5,), name
        loop = [f(*(a[i] for a in args)) for i in range(5)]
        assert all(isinstance(v, float) for v in loop), name
        np.testing.assert_allclose(batched, loop, rtol=1e-12, atol=1e-12, err_msg=name)
    # one ground truth against a batch of estimates broadcasts
    np.testing.assert_allclose(
        mssd(R_e, t_e, R_g[0], t_g[0], pts, SYMS_MIXED),
        [mssd(R_e[i], t_e[i], R_g[0], t_g[0], pts, SYMS_MIXED) for i in range(5)],
        rtol=1e-12,
    )
    with pytest.raises(ValueError, match="batch sizes differ"):
        mssd(R_e, t_e[:3], R_g, t_g, pts, SYMS_MIXED)


def test_mssd_mspd_match_a_plain_loop_over_symmetries() -> None:
    """The chunked (R_e − R_g R_S) evaluation equals transforming the points per symmetry."""
    R_e, t_e, R_g, t_g = _batch(3, seed=2)
    pts = np.random.default_rng(3).normal(size=(200, 3))

    def proj(X: np.ndarray) -> np.ndarray:
        p = X @ K.T
        return p[:, :2] / p[:, 2:]

    for i in range(3):
        est = pts @ R_e[i].T + t_e[i]
        gts = [pts @ (R_g[i] @ Rs).T + R_g[i] @ ts + t_g[i] for Rs, ts in zip(*SYMS_MIXED, strict=True)]
        ref_sd = min(np.linalg.norm(est - g, axis=1).max() for g in gts)
        ref_pd = min(np.linalg.norm(proj(est) - proj(g), axis=1).max() for g in gts)
        assert mssd(R_e[i], t_e[i], R_g[i], t_g[i], pts, SYMS_MIXED) == pytest.approx(ref_sd, rel=1e-12)
        assert mspd(R_e[i], t_e[i], R_g[i], t_g[i], K, pts, SYMS_MIXED) == pytest.approx(ref_pd, rel=1e-12)


def test_torch_inputs_equal_numpy_inputs() -> None:
    torch = pytest.importorskip("torch")
    R_e, t_e, R_g, t_g = _batch()
    T = [torch.as_tensor(a) for a in (R_e, t_e, R_g, t_g)]
    pts = np.random.default_rng(4).normal(size=(100, 3))
    tp, tK = torch.as_tensor(pts, dtype=torch.float32), torch.as_tensor(K)
    torch.testing.assert_close(
        torch.as_tensor(mssd(*T, tp, SYMS_MIXED)),
        torch.as_tensor(mssd(R_e, t_e, R_g, t_g, pts.astype(np.float32), SYMS_MIXED)),
    )
    np.testing.assert_allclose(
        mspd(*T, tK, torch.as_tensor(pts), SYMS_MIXED), mspd(R_e, t_e, R_g, t_g, K, pts, SYMS_MIXED)
    )
    np.testing.assert_allclose(add(*T, torch.as_tensor(pts)), add(R_e, t_e, R_g, t_g, pts))
    np.testing.assert_allclose(re(T[0], T[2]), re(R_e, R_g))
    assert te(T[1][0], T[3][0]) == pytest.approx(te(t_e[0], t_g[0]))
    plate = np.zeros((2, 16, 16))
    plate[:, 4:12, 4:12] = 1000.0
    np.testing.assert_allclose(
        vsd(
            torch.as_tensor(plate),
            torch.as_tensor(plate + 5),
            torch.as_tensor(plate),
            tK,
            15.0,
            [0.04, 0.1],
            100.0,
        ),
        vsd(plate, plate + 5, plate, K, 15.0, [0.04, 0.1], 100.0),
    )


def test_mssd_bounding_sphere_short_cut() -> None:
    """With ``diameter``: inf iff ‖t_e − t_g‖ ≥ diameter (here the shifts are 3, 4 and 5 with d = 4)."""
    R = np.broadcast_to(np.eye(3), (3, 3, 3))
    t_g = np.array([0.0, 0.0, 50.0])
    t_e = t_g + np.array([[3.0, 0, 0], [0, 4.0, 0], [3.0, 4.0, 0]])
    errs = mssd(R, t_e, R, t_g, BOX, None, diameter=4.0)
    np.testing.assert_array_equal(errs, [3.0, np.inf, np.inf])
    np.testing.assert_allclose(mssd(R, t_e, R, t_g, BOX, None), [3.0, 4.0, 5.0])
    assert mssd(R[0], t_e[0], R[0], t_g, BOX, None, diameter=[4.0]) == 3.0
    np.testing.assert_array_equal(
        mssd(R, t_e, R, t_g, BOX, None, diameter=[10.0, 4.0, 6.0]), [3.0, np.inf, 5.0]
    )


def test_sphere_projections_overlap_constructed() -> None:
    """Centres at depth 64, radius 8: threshold 8·(1/64 + 1/64) = 0.25 in x/z, i.e. 16 mm apart (exact in
    binary floating point, so the strict rule shows)."""
    a = np.array([0.0, 0.0, 64.0])
    assert sphere_projections_overlap(8.0, a, a + [15.0, 0, 0]) is True
    assert sphere_projections_overlap(8.0, a, a + [16.0, 0, 0]) is False  # distance == threshold
    assert sphere_projections_overlap(8.0, a, a + [0, -17.0, 0]) is False
    # twice as far: the projection shrinks, the centre moves half as far in the image
    assert sphere_projections_overlap(8.0, a, np.array([16.0, 0, 128.0])) is True  # 0.125 < 8·(1/64 + 1/128)
    both = sphere_projections_overlap(
        [8.0, 8.0, 1.0], a, np.array([[15.0, 0, 64], [16.0, 0, 64], [1.0, 0, 64]])
    )
    np.testing.assert_array_equal(both, [True, False, True])


def test_vsd_short_cut_and_batch() -> None:
    Kc = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    plate = np.zeros((64, 64))
    plate[16:48, 16:48] = 1000.0
    taus = [0.05, 0.1, 0.2]
    t = np.array([0.0, 0.0, 1000.0])
    # identical maps, but the translations say the spheres (radius 50) project far apart → all 1
    assert vsd(plate, plate, plate, Kc, 15.0, taus, 100.0, t_est=t + [500.0, 0, 0], t_gt=t) == [1.0] * 3
    assert vsd(plate, plate, plate, Kc, 15.0, taus, 100.0, t_est=t + [50.0, 0, 0], t_gt=t) == [0.0] * 3
    with pytest.raises(ValueError, match="both"):
        vsd(plate, plate, plate, Kc, 15.0, taus, 100.0, t_est=t)
    back = np.where(plate > 0, 1010.0, 0.0)
    half = plate.copy()
    half[16:48, 32:48] = 0.0
    est = np.stack([plate, back, half, np.zeros_like(plate)])
    gt = np.stack([plate] * 4)
    test = np.stack([plate, np.zeros_like(plate), plate, plate])
    batched = vsd(est, gt, test, Kc, 15.0, taus, [100.0, 100.0, 100.0, 100.0])
    assert batched.shape == (4, 3)
    np.testing.assert_array_equal(batched, [[0, 0, 0], [1, 1, 0], [0.5, 0.5, 0.5], [1, 1, 1]])
    loop = [vsd(est[i], gt[i], test[i], Kc, 15.0, taus, 100.0) for i in range(4)]
    np.testing.assert_array_equal(batched, loop)
    # the short-cut per element of a batch
    t_est = np.array([t, t, t + [500.0, 0, 0], t])
    np.testing.assert_array_equal(
        vsd(est, gt, test, Kc, 15.0, taus, 100.0, t_est=t_est, t_gt=t)[2], [1.0, 1.0, 1.0]
    )
    D = depth_to_distance(np.stack([plate, plate]), np.stack([Kc, Kc]))
    np.testing.assert_array_equal(D[1], depth_to_distance(plate, Kc))
