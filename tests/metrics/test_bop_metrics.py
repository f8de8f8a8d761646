"""BOP pose errors on hand-made cases whose answers follow from the definitions."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from posediff.metrics.bop import add, adi, mspd, mssd, re, symmetry_transforms, te, vsd

TLESS = Path(__file__).resolve().parents[3] / "shared" / "tless" / "models_info_obj1_obj5.json"
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


@pytest.mark.skipif(not TLESS.exists(), reason="shared T-LESS models_info not present")
def test_real_tless_models_info() -> None:
    info = json.loads(TLESS.read_text())
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
