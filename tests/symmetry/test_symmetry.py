"""Symmetry groups of the SYMSOL shapes: exactness, geometry, closed-form distances, invariance."""

import math

import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.lie import SO3
from posediff.lie.so3 import rotation_error
from posediff.symmetry import (
    GOLDEN_RATIO,
    SHAPES,
    canonical_rotation,
    equivalent_rotations,
    is_continuous,
    min_angle_to_equivalents,
    num_modes,
    rotation_angle,
    symmetry_group,
)

F64 = torch.float64
DISCRETE = ("tet", "cube", "icosa")
CONTINUOUS = ("cone", "cyl")
SIZES = {"tet": 12, "cube": 24, "icosa": 60, "cone": 360, "cyl": 720}


def _rand_rot(n: int, seed: int, dtype: torch.dtype = F64) -> Tensor:
    return SO3().sample_uniform((n,), generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _rz(a: Tensor) -> Tensor:
    return SO3().exp(torch.stack([torch.zeros_like(a), torch.zeros_like(a), a], dim=-1))


def _geodesic(A: Tensor, B: Tensor) -> Tensor:
    """Oracle: acos((tr(AᵀB) − 1)/2) (accurate away from 0 and π, which random rotations avoid)."""
    tr = (A * B).sum((-1, -2))
    return torch.acos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0))


def _set_distance(A: Tensor, B: Tensor) -> Tensor:
    """Hausdorff distances between point sets (…, n, 3) and (…, m, 3) → (…,)."""
    d = (A[..., :, None, :] - B[..., None, :, :]).norm(dim=-1)
    return torch.maximum(d.min(-2).values.amax(-1), d.min(-1).values.amax(-1))


def _vertices(shape: str) -> Tensor:
    if shape == "tet":
        v = [(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)]
    elif shape == "cube":
        v = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    else:
        p = GOLDEN_RATIO
        base = [(0, s1, s2 * p) for s1 in (-1, 1) for s2 in (-1, 1)]
        v = [c for (a, b, cc) in base for c in ((a, b, cc), (cc, a, b), (b, cc, a))]
    return torch.tensor(v, dtype=F64)


# ----------------------------------------------------------------------------- the groups
@pytest.mark.parametrize("shape", SHAPES)
def test_group_size_identity_and_rotations(shape: str) -> None:
    G = symmetry_group(shape)
    assert G.shape == (SIZES[shape], 3, 3) and G.dtype == F64
    assert torch.equal(G[0], torch.eye(3, dtype=F64))
    assert rotation_error(G).max() < 1e-12
    # no duplicates
    d = (G[:, None] - G[None]).abs().flatten(-2).amax(-1) + 10 * torch.eye(len(G), dtype=F64)
    assert d.min() > 1e-3
    assert num_modes(shape) == (None if shape in CONTINUOUS else SIZES[shape])
    assert is_continuous(shape) == (shape in CONTINUOUS)


@pytest.mark.parametrize("shape", SHAPES)
def test_closure(shape: str) -> None:
    G = symmetry_group(shape)
    if shape in DISCRETE:
        P = (G[:, None] @ G[None]).reshape(-1, 3, 3)
    else:  # a random subset of the products
        g = torch.Generator().manual_seed(1)
        i, j = torch.randint(len(G), (2, 300), generator=g)
        P = G[i] @ G[j]
    dist = (P[:, None] - G[None]).abs().flatten(-2).amax(-1).min(-1).values
    assert dist.max() < 1e-12
    # closed under inverse too
    inv = (G.mT[:, None] - G[None]).abs().flatten(-2).amax(-1).min(-1).values
    assert inv.max() < 1e-12


@pytest.mark.parametrize("shape", DISCRETE)
def test_group_maps_vertices_onto_themselves(shape: str) -> None:
    V = _vertices(shape)
    assert len(V) == {"tet": 4, "cube": 8, "icosa": 12}[shape]
    G = symmetry_group(shape)
    assert _set_distance(V @ G.mT, V.expand(len(G), -1, -1)).max() < 1e-9


def test_icosa_vertices_are_regular() -> None:
    V = _vertices("icosa")
    d = torch.cdist(V, V)
    # every vertex has 5 nearest neighbours at distance 2
    assert ((d - 2.0).abs() < 1e-12).sum(-1).tolist() == [5] * 12


def test_dtype_device_step_and_fresh_copy() -> None:
    G = symmetry_group("icosa", dtype=torch.float32)
    assert G.dtype == torch.float32
    G.zero_()  # a fresh copy: the cache is untouched
    assert symmetry_group("icosa")[0, 0, 0] == 1.0
    assert symmetry_group("cone", step_deg=5.0).shape == (72, 3, 3)
    assert symmetry_group("cyl", step_deg=2.0).shape == (360, 3, 3)
    with pytest.raises(ValueError):
        symmetry_group("cone", step_deg=7.0)
    with pytest.raises(ValueError):
        symmetry_group("sphere")


def test_equivalent_rotations() -> None:
    R = _rand_rot(5, 2)
    for shape in SHAPES:
        E = equivalent_rotations(shape, R)
        assert E.shape == (5, SIZES[shape], 3, 3)
        assert_close(E[:, 0], R)
        assert_close(E, R[:, None] @ symmetry_group(shape)[None])
    assert equivalent_rotations("cone", R, step_deg=10.0).shape == (5, 36, 3, 3)


# ----------------------------------------------------------------------------- distances
@pytest.mark.parametrize("shape", SHAPES)
def test_min_angle_zero_on_equivalents(shape: str) -> None:
    R = _rand_rot(4, 3)
    E = equivalent_rotations(shape, R)  # (4, S, 3, 3)
    ang = min_angle_to_equivalents(shape, E, R)
    assert ang.shape == E.shape[:2]
    assert ang.max() < 1e-6


@pytest.mark.parametrize("shape", CONTINUOUS)
def test_continuous_invariance(shape: str) -> None:
    R = _rand_rot(64, 4)
    alpha = (torch.rand(64, generator=torch.Generator().manual_seed(5), dtype=F64) - 0.5) * 2 * math.pi
    assert min_angle_to_equivalents(shape, R @ _rz(alpha), R).max() < 1e-7
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))
    flipped = min_angle_to_equivalents(shape, R @ flip @ _rz(alpha), R)
    if shape == "cyl":
        assert flipped.max() < 1e-7
        # a flip about an arbitrary horizontal axis (cos β, sin β, 0)
        beta = alpha.flip(0)
        axis = torch.stack([beta.cos(), beta.sin(), torch.zeros_like(beta)], dim=-1)
        assert min_angle_to_equivalents(shape, R @ SO3().exp(math.pi * axis), R).max() < 1e-7
    else:  # the cone has no flip: every Rx(π)·Rz(α) is a rotation by π
        assert_close(flipped, torch.full_like(flipped, math.pi))


@pytest.mark.parametrize("shape", CONTINUOUS)
def test_closed_form_matches_grid(shape: str) -> None:
    R_gt = _rand_rot(8, 6)
    R_est = _rand_rot(8 * 12, 7).reshape(8, 12, 3, 3)
    exact = min_angle_to_equivalents(shape, R_est, R_gt)
    E = equivalent_rotations(shape, R_gt)  # (32, S, 3, 3), 1° grid
    grid = _geodesic(E[:, None], R_est[:, :, None]).min(-1).values
    assert exact.shape == grid.shape == (8, 12)
    assert (exact <= grid + 1e-10).all()
    assert (grid - exact).max() <= math.radians(0.5) + 1e-10
    # close estimates: the grid error is visible, the exact one is not
    near = R_gt @ _rz(torch.full((8,), math.radians(0.5), dtype=F64))
    assert min_angle_to_equivalents(shape, near, R_gt).max() < 1e-7
    assert grid.min() >= 0.0


@pytest.mark.parametrize("shape", DISCRETE)
def test_discrete_min_angle_matches_brute_force(shape: str) -> None:
    R_gt = _rand_rot(16, 8)
    R_est = _rand_rot(16 * 10, 9).reshape(16, 10, 3, 3)
    E = equivalent_rotations(shape, R_gt)
    brute = _geodesic(E[:, None], R_est[:, :, None]).min(-1).values
    assert_close(min_angle_to_equivalents(shape, R_est, R_gt), brute)
    # broadcast form: same batch shape, no sample dimension
    assert_close(min_angle_to_equivalents(shape, R_est[:, 0], R_gt), brute[:, 0])


@pytest.mark.parametrize("shape", SHAPES)
def test_small_offset_is_exact_and_float32_stable(shape: str) -> None:
    R = _rand_rot(8, 10)
    delta = 1e-4
    axis = torch.tensor([1.0, 0.0, 0.0], dtype=F64)  # a tilt of the symmetry axis, for cone/cyl too
    off = R @ SO3().exp(delta * axis).expand(8, 3, 3)
    assert_close(min_angle_to_equivalents(shape, off, R), torch.full((8,), delta, dtype=F64))
    a32 = min_angle_to_equivalents(shape, R.float(), R.float())
    assert a32.dtype == torch.float32 and a32.max() < 1e-3


def test_rotation_angle_at_zero_and_pi() -> None:
    phi = torch.tensor([[0.0, 0.0, 0.0], [1e-9, 0.0, 0.0], [0.0, math.pi, 0.0], [0.3, -0.2, 0.5]], dtype=F64)
    assert_close(rotation_angle(SO3().exp(phi)), phi.norm(dim=-1))


# ----------------------------------------------------------------------------- canonical rotation
@pytest.mark.parametrize("shape", SHAPES)
def test_canonical_rotation_invariant(shape: str) -> None:
    n = 64
    R = _rand_rot(n, 11)
    gen = torch.Generator().manual_seed(12)
    if shape in DISCRETE:
        G = symmetry_group(shape)
        S = G[torch.randint(len(G), (n,), generator=gen)]
    else:
        S = _rz((torch.rand(n, generator=gen, dtype=F64) - 0.5) * 2 * math.pi)
        if shape == "cyl":
            flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))
            S = torch.where((torch.arange(n) % 2 == 0)[:, None, None], flip @ S, S)
    C = canonical_rotation(shape, R)
    assert_close(canonical_rotation(shape, R @ S), C)
    assert rotation_error(C).max() < 1e-12
    # C is one of the equivalents of R, and the one closest to the identity
    assert min_angle_to_equivalents(shape, C, R).max() < 1e-7
    eye = torch.eye(3, dtype=F64).expand(n, 3, 3)
    assert_close(rotation_angle(C), min_angle_to_equivalents(shape, eye, R))
