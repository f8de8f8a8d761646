"""The symmetric-shape toy data: conditions are symmetry-invariant, targets are the equivalent sets."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.data import SymmetryToy
from posediff.data.toy import spread_poses
from posediff.symmetry import SHAPES, canonical_rotation, min_angle_to_equivalents


@pytest.mark.parametrize("shape", SHAPES)
def test_spread_poses_are_canonical_deterministic_and_far_apart(shape: str) -> None:
    poses = spread_poses(shape, 4, seed=7)
    assert poses.shape == (4, 3, 3) and poses.dtype == torch.float64
    assert_close(poses, spread_poses(shape, 4, seed=7), rtol=0, atol=0)
    assert_close(canonical_rotation(shape, poses), poses)
    sep = min(
        float(min_angle_to_equivalents(shape, poses[i][None], poses[j]).squeeze())
        for i in range(4)
        for j in range(i + 1, 4)
    )
    # farther apart than plain random draws are likely to be; the icosahedron's fundamental
    # domain is the smallest (1/60 of SO(3))
    assert math.degrees(sep) > 30.0, f"{shape}: closest pair {math.degrees(sep):.1f}°"


@pytest.mark.parametrize("group", ["so3", "se3"])
def test_toy_conditions_are_invariant_and_poses_cover_the_equivalent_set(group: str) -> None:
    data = SymmetryToy(group, 600, shapes=("cube", "cone"), seed=3, num_poses=2)
    shape_names = ("cube", "cone")
    # the condition depends only on the canonical pose (and translation), not on the symmetry drawn
    for shape in shape_names:
        sel = data.shape == SHAPES.index(shape)  # global ids, as SYMSOL's
        canon = canonical_rotation(shape, data.rotation[sel].double())
        assert_close(data.cond[sel][:, 5:14].double(), canon.flatten(-2), atol=1e-5, rtol=0)
        distinct = torch.unique(canon.flatten(-2).round(decimals=3), dim=0)
        assert len(distinct) == 2  # num_poses fixed poses per shape
    cube = data.rotation[data.shape == SHAPES.index("cube")].double()
    # every cube sample is one of the 2 × 24 equivalent poses, and most of them occur
    base = spread_poses("cube", 2, 12345)
    angles = torch.stack([min_angle_to_equivalents("cube", cube, b) for b in base]).min(0).values
    assert float(angles.max()) < 1e-3
    assert len(torch.unique(cube.flatten(-2).round(decimals=3), dim=0)) > 40  # of the 48
    if group == "se3":
        t = data.translation
        assert float(t.abs().max()) <= 1.0 and float(t.abs().min()) >= 0.0
        assert_close(data.pose[:, :3, 3], t.to(data.pose.dtype))
