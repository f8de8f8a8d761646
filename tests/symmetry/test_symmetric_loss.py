"""The symmetry-aware regression loss: zero on every equivalent pose, the chordal distance to the nearest
one elsewhere, finite gradients everywhere (including on the equivalents and the closed form's corner)."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.lie import SO3
from posediff.symmetry import (
    SHAPES,
    is_continuous,
    min_angle_to_equivalents,
    set_chordal_sq,
    symmetric_chordal_sq,
    symmetry_group,
    symsol_chordal_sq,
)

F64 = torch.float64


def _rand(n: int, seed: int) -> torch.Tensor:
    return SO3().sample_uniform((n,), generator=torch.Generator().manual_seed(seed), dtype=F64)


def _rz(a: torch.Tensor) -> torch.Tensor:
    return SO3().exp(torch.stack([torch.zeros_like(a), torch.zeros_like(a), a], dim=-1))


@pytest.mark.parametrize("shape", SHAPES)
def test_zero_on_every_equivalent_pose(shape: str) -> None:
    R = _rand(8, 0)
    G = symmetry_group(shape, dtype=F64)
    if is_continuous(shape):  # off-grid angles too: the closed form is exact, not the 1° grid
        a = torch.rand(50, generator=torch.Generator().manual_seed(1), dtype=F64) * 2 * math.pi
        G = torch.cat(
            [G, _rz(a)]
            + ([torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)) @ _rz(a)] if shape == "cyl" else [])
        )
    eq = R[:, None] @ G[None]
    loss = symmetric_chordal_sq(shape, eq, R)
    assert loss.abs().max() < 1e-12


@pytest.mark.parametrize("shape", SHAPES)
def test_chordal_distance_to_the_nearest_equivalent_off_it(shape: str) -> None:
    R, Q = _rand(64, 2), _rand(64, 3)
    loss = symmetric_chordal_sq(shape, Q, R)
    angle = min_angle_to_equivalents(shape, Q, R)
    assert_close(loss, 8.0 * torch.sin(angle / 2.0) ** 2, atol=1e-12, rtol=0)
    assert (loss > 1e-6).all()
    # a small turn off an equivalent pose is penalised
    small = R @ SO3().exp(torch.tensor([0.0, 0.05, 0.0], dtype=F64))
    if shape != "cone" and shape != "cyl":
        assert (symmetric_chordal_sq(shape, small, R) > 1e-3).all()
    else:  # a turn about a horizontal axis moves the symmetry axis
        assert (symmetric_chordal_sq(shape, small, R) > 1e-3).all()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("shape", SHAPES)
def test_gradients_finite_on_and_off_the_equivalents(shape: str, dtype: torch.dtype) -> None:
    R = _rand(6, 4).to(dtype)
    G = symmetry_group(shape, dtype=dtype)
    cases = [R @ G[1], _rand(6, 5).to(dtype), R]
    # the closed form's corner: M = Rᵀ R̂ with a vanishing xy block (the axis turned by π/2)
    cases.append(R @ SO3().exp(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=dtype)))
    for est in cases:
        est = est.clone().requires_grad_(True)
        symmetric_chordal_sq(shape, est, R).sum().backward()
        assert torch.isfinite(est.grad).all()


def test_mixed_batch_and_samples_dimension() -> None:
    R, Q = _rand(10, 6), _rand(10 * 3, 7).view(10, 3, 3, 3)
    ids = torch.arange(10) % len(SHAPES)
    out = symsol_chordal_sq(ids, Q, R)
    assert out.shape == (10, 3)
    for i in range(10):
        assert_close(out[i], symmetric_chordal_sq(SHAPES[int(ids[i])], Q[i], R[i]))


def test_set_version_matches_the_finite_groups_with_padding() -> None:
    R, Q = _rand(4, 8), _rand(4, 9)
    tet, cube = symmetry_group("tet", dtype=F64), symmetry_group("cube", dtype=F64)
    sym = torch.zeros(4, 24, 3, 3, dtype=F64)
    mask = torch.zeros(4, 24, dtype=torch.bool)
    for i in range(4):
        g = tet if i % 2 == 0 else cube
        sym[i, : len(g)], mask[i, : len(g)] = g, True
    out = set_chordal_sq(Q, R, sym, mask)
    ref = torch.stack([symmetric_chordal_sq("tet" if i % 2 == 0 else "cube", Q[i], R[i]) for i in range(4)])
    assert_close(out, ref)
    assert set_chordal_sq(R[:, None] @ sym[:, :1], R, sym, mask).abs().max() < 1e-12


# ----------------------------------------------------------------------------- invariant embeddings
from posediff.symmetry import decode_embedding, embedding_dim, invariant_embedding  # noqa: E402


@pytest.mark.parametrize("shape", SHAPES)
def test_embedding_is_invariant_exactly_under_the_group(shape: str) -> None:
    R = _rand(16, 10)
    G = symmetry_group(shape, dtype=F64, step_deg=7.5)
    phi = invariant_embedding(shape, R)
    assert phi.shape == (16, embedding_dim(shape)) and embedding_dim(shape) == 48
    eq = invariant_embedding(shape, R[:, None] @ G[None])
    assert (eq - phi[:, None]).abs().max() < 1e-12


@pytest.mark.parametrize("shape", SHAPES)
def test_embedding_separates_poses_that_are_not_equivalent(shape: str) -> None:
    """Injective modulo the group: a pose's embedding is decoded to an equivalent pose, and poses
    away from every equivalent have distinct embeddings."""
    R = _rand(24, 11)
    back = decode_embedding(shape, invariant_embedding(shape, R).float())
    assert torch.rad2deg(min_angle_to_equivalents(shape, back.double(), R)).max() < 1.5
    Q = _rand(24, 12)
    far = min_angle_to_equivalents(shape, Q, R) > 0.2
    gap = (invariant_embedding(shape, Q) - invariant_embedding(shape, R)).norm(dim=-1)
    assert (gap[far] > 1e-3).all()


@pytest.mark.parametrize("shape", SHAPES)
def test_embedding_is_continuous_and_has_finite_gradients(shape: str) -> None:
    R = _rand(8, 13)
    small = SO3().exp(torch.full((8, 3), 1e-6, dtype=F64))
    assert (invariant_embedding(shape, R @ small) - invariant_embedding(shape, R)).abs().max() < 1e-4
    x = torch.zeros(8, 3, dtype=F64, requires_grad=True)
    invariant_embedding(shape, R @ SO3().exp(x)).square().sum().backward()
    assert torch.isfinite(x.grad).all()


def test_pose_encoder_embedding_loss_is_zero_at_the_truth_and_needs_its_shapes() -> None:
    from posediff.nn import Encoding, PoseEncoder

    enc = PoseEncoder(
        image_size=32, out_dim=8, translation=False, rotation_head="invariant", shapes=["tet", "cube"]
    )
    R = _rand(4, 14).float()
    ids = torch.tensor([0, 1, 0, 1])  # tet, cube (indices in SHAPES)
    emb = torch.zeros(4, 48 + 48)
    emb[ids == 0, :48] = invariant_embedding("tet", R[ids == 0])
    emb[ids == 1, 48:] = invariant_embedding("cube", R[ids == 1])
    logits = torch.full((4, 2), -30.0)
    logits[torch.arange(4), ids] = 30.0
    out = Encoding(torch.zeros(4, 8), None, embedding=emb, shape_logits=logits)
    assert enc.embedding_loss(out, ids, R).abs().max() < 1e-5
    decoded = enc.decode(emb, logits)
    for i, name in enumerate(["tet", "cube", "tet", "cube"]):
        assert torch.rad2deg(min_angle_to_equivalents(name, decoded[i].double(), R[i].double())) < 1.5
    with pytest.raises(ValueError, match="covers"):
        enc.embedding_loss(out, torch.tensor([0, 1, 2, 3]), R)


@pytest.mark.parametrize("shape", SHAPES)
def test_standardised_embedding_has_one_spread_and_round_trips(shape: str) -> None:
    from posediff.symmetry import STANDARD_EMBEDDING_SPREAD, standardise_embedding, unstandardise_embedding

    R = _rand(4096, 15)  # other draws than the statistics' own
    z = standardise_embedding(shape, invariant_embedding(shape, R))
    spread = z.square().sum(-1).mean().sqrt().item()
    assert abs(spread - STANDARD_EMBEDDING_SPREAD) < 0.05 * STANDARD_EMBEDDING_SPREAD  # (measured ≤ 1 %)
    assert z.mean(0).norm().item() < 0.05 * STANDARD_EMBEDDING_SPREAD  # centred
    assert_close(unstandardise_embedding(shape, z), invariant_embedding(shape, R))
    G = symmetry_group(shape, dtype=F64, step_deg=7.5)  # still invariant
    eq = standardise_embedding(shape, invariant_embedding(shape, R[:8, None] @ G[None]))
    assert (eq - z[:8, None]).abs().max() < 1e-10


def test_raw_embeddings_differ_in_spread_by_far_more_than_the_standardised() -> None:
    """Why the standardisation exists: the icosahedron's raw φ varies ~18× less than the cone's."""
    from posediff.symmetry import embedding_statistics

    spreads = {s: embedding_statistics(s)[1] for s in SHAPES}
    assert spreads["icosa"] < 0.3 < 3.5 < spreads["cone"]


def test_pose_encoder_haar_targets_are_standardised_and_decoded_back() -> None:
    from posediff.nn import Encoding, PoseEncoder
    from posediff.symmetry import standardise_embedding

    enc = PoseEncoder(image_size=32, out_dim=8, translation=False, rotation_head="invariant",
                      shapes=["icosa", "cube"], embedding_scale="haar")  # fmt: skip
    R = _rand(4, 16).float()
    ids = torch.tensor([2, 1, 2, 1])  # icosa, cube (indices in SHAPES)
    emb = torch.zeros(4, 96)
    emb[ids == 2, :48] = standardise_embedding("icosa", invariant_embedding("icosa", R[ids == 2]))
    emb[ids == 1, 48:] = standardise_embedding("cube", invariant_embedding("cube", R[ids == 1]))
    logits = torch.full((4, 2), -30.0)
    logits[torch.arange(4), torch.tensor([0, 1, 0, 1])] = 30.0
    out = Encoding(torch.zeros(4, 8), None, embedding=emb, shape_logits=logits)
    assert enc.embedding_loss(out, ids, R).abs().max() < 1e-4
    raw = PoseEncoder(
        image_size=32, out_dim=8, translation=False, rotation_head="invariant", shapes=["icosa", "cube"]
    )
    assert raw.embedding_loss(out, ids, R).min() > 1.0  # the raw head reads the same outputs as wrong
    decoded = enc.decode(emb, logits)
    for i, name in enumerate(["icosa", "cube", "icosa", "cube"]):
        assert torch.rad2deg(min_angle_to_equivalents(name, decoded[i].double(), R[i].double())) < 1.5
    with pytest.raises(ValueError, match="embedding_scale"):
        PoseEncoder(
            image_size=32, out_dim=8, translation=False, rotation_head="invariant", embedding_scale="unit"
        )
