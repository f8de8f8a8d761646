"""SymmetrySet: one value for the symmetries of a SYMSOL shape or a BOP object, and the one smallest
angle over them that every metric uses."""

import math

import numpy as np
import pytest
import torch

from posediff.lie import SO3
from posediff.metrics import bop19
from posediff.metrics.pose import mode_coverage, rotation_errors_deg
from posediff.symmetry import SHAPES, SymmetrySet, as_symmetry_set, min_angle_to_equivalents, symmetry_group

CYLINDER = {  # a BOP models_info entry: continuous about z through (0, 0, 5), and a flip about x
    "diameter": 80.0,
    "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 5]}],
    "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 10, 0, 0, 0, 1]],
}


def _rotations(n: int, seed: int = 0) -> torch.Tensor:
    return SO3().sample_uniform((n,), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_a_bop_entry_discretises_as_the_toolkit() -> None:
    s = SymmetrySet.from_models_info(CYLINDER, name="obj_000001")
    assert s.is_continuous and len(s) == 2 and s.num_modes is None
    R, t = s.transforms(0.01)
    n = math.ceil(math.pi / 0.01)
    assert R.shape == (2 * n, 3, 3) and t.shape == (2 * n, 3)
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-15)  # the identity first (k = 0 is included)
    np.testing.assert_allclose(t[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(R[n], np.diag([1.0, -1.0, -1.0]), atol=1e-15)  # then the flip, unturned
    np.testing.assert_allclose(t[n], [0.0, 0.0, 10.0], atol=1e-12)
    # a member of a continuous axis through o keeps o fixed: R o + t = o
    o = np.array([0.0, 0.0, 5.0])
    np.testing.assert_allclose(
        np.einsum("sij,j->si", R[:n], o) + t[:n], np.broadcast_to(o, (n, 3)), atol=1e-12
    )
    assert np.allclose(np.einsum("sij,skj->sik", R, R), np.eye(3), atol=1e-12)  # rotations
    with pytest.raises(ValueError, match="not 16"):
        SymmetrySet.from_models_info({"symmetries_discrete": [[1, 0, 0]]})
    with pytest.raises(ValueError, match="zero axis"):
        SymmetrySet.from_models_info({"symmetries_continuous": [{"axis": [0, 0, 0]}]})


@pytest.mark.parametrize("shape", SHAPES)
def test_symsol_sets_are_the_exact_groups(shape: str) -> None:
    s = SymmetrySet.from_shape(shape)
    assert s.shape == shape and s.is_continuous == (shape in ("cone", "cyl"))
    np.testing.assert_array_equal(s.rotations(step_deg=2.0), symmetry_group(shape, step_deg=2.0).numpy())
    R_gt, R_est = _rotations(6, 1), _rotations(6, 2)
    exact = torch.rad2deg(min_angle_to_equivalents(shape, R_est, R_gt))
    torch.testing.assert_close(s.min_angle_deg(R_est, R_gt), exact)  # torch in, torch out, exact
    np.testing.assert_allclose(s.min_angle_deg(R_est.numpy(), R_gt.numpy()), exact.numpy(), atol=1e-9)
    # every metric takes the set as well as the name
    samples = R_est[:, None].expand(6, 3, 3, 3)
    torch.testing.assert_close(
        rotation_errors_deg(s, samples, R_gt), rotation_errors_deg(shape, samples, R_gt)
    )
    torch.testing.assert_close(
        mode_coverage(s, samples, R_gt), mode_coverage(shape, samples, R_gt), equal_nan=True
    )
    assert as_symmetry_set(shape) is s  # cached: one value per shape


def test_the_smallest_angle_over_a_bop_set_is_the_metrics() -> None:
    s = SymmetrySet.from_models_info(CYLINDER)
    R_gt = _rotations(5, 3)
    turn = SO3().exp(torch.tensor([0.0, 0.0, 1.234], dtype=torch.float64))  # any turn about the axis
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    tilt = SO3().exp(torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64))
    for M, expected in ((turn, 0.0), (flip @ turn, 0.0), (turn @ tilt, math.degrees(0.1))):
        R_est = R_gt @ M
        got = s.min_angle_deg(R_est.numpy(), R_gt.numpy())
        np.testing.assert_allclose(got, expected, atol=0.3)  # the 0.01-rad grid: ≤ 0.29° above the exact
        np.testing.assert_allclose(bop19.symmetric_rotation_errors_deg(R_est, R_gt, s), got)
        np.testing.assert_allclose(bop19.symmetric_rotation_errors_deg(R_est, R_gt, s.transforms()), got)
        torch.testing.assert_close(s.min_angle_deg(R_est, R_gt), torch.from_numpy(got))
    # arccos of a trace: ~√ε rad at 0, as the BOP toolkit's re()
    assert SymmetrySet.identity().min_angle_deg(R_gt.numpy(), R_gt.numpy()).max() < 1e-5


def test_conversions() -> None:
    assert as_symmetry_set(None).num_modes == 1
    pair = as_symmetry_set((np.stack([np.eye(3), np.diag([-1.0, -1, 1])]), np.zeros((2, 3))))
    assert pair.num_modes == 2 and not pair.is_continuous
    with pytest.raises(ValueError, match="unknown SYMSOL shape"):
        as_symmetry_set("sphere")
    assert "2 finite members" in repr(pair)
