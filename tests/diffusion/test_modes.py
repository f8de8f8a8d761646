"""Tests for ``posediff.diffusion.modes``: clustering pose samples into weighted modes."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion.modes import Modes, modes
from posediff.lie import R3SO3, SE2, SE3, SO3, LieGroup

DEG = math.pi / 180.0


def rot_angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle of the relative rotation between the rotation blocks of ``a`` and ``b``, in degrees."""
    ra, rb = a[..., :3, :3].double(), b[..., :3, :3].double()
    return SO3().rminus(ra, rb).norm(dim=-1) / DEG


def separated_rotations(n: int, min_deg: float, gen: torch.Generator) -> torch.Tensor:
    """``n`` random rotations, pairwise more than ``min_deg`` apart (rejection sampling)."""
    out: list[torch.Tensor] = []
    while len(out) < n:
        r = SO3().sample_uniform((), generator=gen, dtype=torch.float64)
        if all(float(rot_angle_deg(r, q)) > min_deg for q in out):
            out.append(r)
    return torch.stack(out)


def noisy(
    group: LieGroup, centres: torch.Tensor, counts: list[int], sigma: list[float], gen: torch.Generator
):
    """``counts[i]`` samples ``centres[i] · Exp(N(0, diag(sigma)²))``, shuffled; returns samples, true labels."""
    labels = torch.cat([torch.full((c,), i) for i, c in enumerate(counts)])
    perm = torch.randperm(labels.shape[0], generator=gen)
    labels = labels[perm]
    z = torch.randn(labels.shape[0], group.dim, generator=gen, dtype=torch.float64)
    z = z * torch.tensor(sigma, dtype=torch.float64)
    return group.rplus(centres[labels], z), labels


def karcher_reference(group: LieGroup, x: torch.Tensor, iters: int = 50) -> torch.Tensor:
    """The Fréchet mean of ``x`` by a long plain iteration (independent of the module's batched one)."""
    m = x[0]
    for _ in range(iters):
        m = group.rplus(m, group.rminus(m.expand_as(x), x).mean(0))
    return m


@pytest.fixture(scope="module")
def twelve() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]:
    gen = torch.Generator().manual_seed(1)
    centres = separated_rotations(12, 40.0, gen)
    counts = [300, 200] + [50] * 10
    x, labels = noisy(SO3(), centres, counts, [2 * DEG] * 3, gen)
    return x, labels, centres, counts


def match(m: Modes, centres: torch.Tensor) -> torch.Tensor:
    """For each mode, the index of the nearest true centre (must be a bijection)."""
    idx = rot_angle_deg(m.poses[:, None], centres[None]).argmin(1)
    assert sorted(idx.tolist()) == list(range(centres.shape[0]))
    return idx


def test_twelve_so3_modes(twelve) -> None:
    x, labels, centres, counts = twelve
    m = modes(x, SO3())
    assert isinstance(m, Modes) and len(m) == 12
    idx = match(m, centres)
    # weights are the true fractions (the clusters are recovered exactly)
    truth = torch.tensor(counts, dtype=torch.float64) / sum(counts)
    assert_close(m.weights, truth[idx], atol=0.03, rtol=0)
    assert_close(m.weights.sum(), torch.tensor(1.0, dtype=torch.float64))
    assert m.counts.dtype == torch.long and int(m.counts.sum()) == x.shape[0]
    assert torch.all(m.weights[:-1] >= m.weights[1:])
    # the partition is the generating one
    assert m.labels.dtype == torch.long and m.labels.shape == (x.shape[0],)
    assert torch.equal(idx[m.labels], labels)
    # each pose is the Fréchet mean of its cluster (to 1e-6°) ...
    for k in range(len(m)):
        ref = karcher_reference(SO3(), x[m.labels == k])
        assert float(rot_angle_deg(m.poses[k], ref)) < 1e-6
    # ... which is near the true centre up to the sampling error of a mean of n samples with 2° noise
    # per axis, 2°·√(3/n) on average (0.49° for n = 50): a 0.5° bound would fail for about a third of
    # the small clusters, so the bound is 4.5 standard errors per axis (chance of failure < 1e-3).
    err = rot_angle_deg(m.poses, centres[idx])
    bound = 4.5 * 2.0 / m.counts.double().sqrt()
    assert torch.all(err < bound), (err, bound)
    assert float(err[m.counts == 300]) < 0.5


def test_summary_and_repr(twelve) -> None:
    x, *_ = twelve
    m = modes(x, SO3())
    assert m.summary() == "12 modes: weights 0.300 … 0.050"
    assert repr(m) == "Modes(12 modes: weights 0.300 … 0.050)"


@pytest.mark.parametrize("group", [SE3(), R3SO3()], ids=lambda g: g.name)
def test_translation_separates(group: LieGroup) -> None:
    gen = torch.Generator().manual_seed(2)
    r = SO3().sample_uniform((), generator=gen, dtype=torch.float64)
    c = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c[:, :3, :3] = r
    c[1, :3, 3] = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64)  # 1.0 apart
    x, labels = noisy(group, c, [200, 200], [0.01] * 3 + [2 * DEG] * 3, gen)
    m = modes(x, group)
    assert len(m) == 2
    assert_close(m.weights, torch.full((2,), 0.5, dtype=torch.float64))
    idx = (m.poses[:, None, :3, 3] - c[None, :, :3, 3]).norm(dim=-1).argmin(1)
    assert sorted(idx.tolist()) == [0, 1]
    assert torch.equal(idx[m.labels], labels)
    assert_close(m.poses[:, :3, 3], c[idx, :3, 3], atol=0.01, rtol=0)
    assert float(rot_angle_deg(m.poses, c[idx]).max()) < 1.0
    # a translation radius above the separation merges them, directly or through the weight
    assert len(modes(x, group, translation_radius=2.0)) == 1
    assert len(modes(x, group, translation_weight=0.1)) == 1  # radius 10° / 0.1 = 1.75 units


@pytest.mark.parametrize("group", [SE3(), R3SO3()], ids=lambda g: g.name)
def test_rotation_separates(group: LieGroup) -> None:
    gen = torch.Generator().manual_seed(3)
    c = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c[:, :3, 3] = torch.tensor([0.1, -0.2, 0.5], dtype=torch.float64)
    c[1, :3, :3] = SO3().exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    x, labels = noisy(group, c, [150, 250], [0.005] * 3 + [2 * DEG] * 3, gen)
    m = modes(x, group)
    assert len(m) == 2
    assert_close(m.weights, torch.tensor([0.625, 0.375], dtype=torch.float64))
    idx = rot_angle_deg(m.poses[:, None], c[None]).argmin(1)
    assert idx.tolist() == [1, 0]
    assert torch.equal(idx[m.labels], labels)
    assert float(rot_angle_deg(m.poses, c[idx]).max()) < 1.0
    # the same samples with only the translations compared would be one mode
    assert len(modes(x, group, radius_deg=180.0)) == 1


def test_single_tight_cluster() -> None:
    gen = torch.Generator().manual_seed(4)
    c = SE3().sample_uniform(1, generator=gen, dtype=torch.float64)
    x, _ = noisy(SE3(), c, [500], [1e-3] * 3 + [0.5 * DEG] * 3, gen)
    m = modes(x, SE3())
    assert len(m) == 1 and m.poses.shape == (1, 4, 4)
    assert_close(m.weights, torch.ones(1, dtype=torch.float64))
    assert m.counts.tolist() == [500] and m.dropped == 0.0
    assert torch.all(m.labels == 0)
    assert_close(m.poses[0], karcher_reference(SE3(), x), atol=1e-9, rtol=0)
    assert m.summary() == "1 mode: weight 1.000"


@pytest.mark.parametrize("group", [SO3(), SE3()], ids=lambda g: g.name)
def test_near_pi(group: LieGroup) -> None:
    """Samples around a rotation of angle π − 1e-3 straddle the principal-log boundary."""
    gen = torch.Generator().manual_seed(5)
    axis = torch.tensor([1.0, 2.0, -2.0], dtype=torch.float64) / 3.0
    c = torch.eye(group.matrix_dim, dtype=torch.float64)[None].clone()
    c[0, :3, :3] = SO3().exp(axis * (math.pi - 1e-3))
    sigma = [2 * DEG] * 3 if group.dim == 3 else [0.01] * 3 + [2 * DEG] * 3
    x, _ = noisy(group, c, [400], sigma, gen)
    phi = SO3().log(x[:, :3, :3])
    assert float((phi @ axis).min()) < 0 < float((phi @ axis).max())  # both sides of π
    m = modes(x, group)
    assert len(m) == 1
    assert float(rot_angle_deg(m.poses[0], c[0])) < 0.5
    assert float(rot_angle_deg(m.poses[0], karcher_reference(group, x))) < 1e-6


def test_max_modes_and_min_weight(twelve) -> None:
    x, *_ = twelve
    m = modes(x, SO3(), max_modes=3)
    assert len(m) == 3 and m.counts.tolist() == [300, 200, 50]
    assert_close(m.weights, torch.tensor([300.0, 200.0, 50.0], dtype=torch.float64) / 550)
    assert m.dropped == pytest.approx(0.45)
    assert int((m.labels == -1).sum()) == 450
    assert torch.equal(torch.bincount(m.labels[m.labels >= 0]), m.counts)
    assert m.summary() == "3 modes: weights 0.545 … 0.091 (45.0% of samples dropped)"

    m = modes(x, SO3(), min_weight=0.1)
    assert m.counts.tolist() == [300, 200]
    assert_close(m.weights, torch.tensor([0.6, 0.4], dtype=torch.float64))
    assert m.dropped == pytest.approx(0.5)

    full = modes(x, SO3())
    m = modes(x, SO3(), min_weight=0.04, max_modes=100)
    assert len(m) == 12 and m.dropped == 0.0
    assert torch.equal(m.labels, full.labels) and torch.equal(m.poses, full.poses)

    m = modes(x, SO3(), min_weight=1.0)
    assert len(m) == 0 and m.poses.shape == (0, 3, 3) and m.dropped == 1.0
    assert torch.all(m.labels == -1)
    assert m.summary() == "0 modes (100.0% of samples dropped)"


def test_float32(twelve) -> None:
    x, labels, centres, _ = twelve
    m64 = modes(x, SO3())
    m = modes(x.float(), SO3())
    assert m.poses.dtype == torch.float32 and m.weights.dtype == torch.float32
    assert m.counts.dtype == torch.long and m.labels.dtype == torch.long
    assert torch.equal(m.labels, m64.labels)
    assert_close(m.weights, m64.weights.float())
    assert_close(m.poses, m64.poses.float(), atol=1e-5, rtol=0)
    SO3().check(m.poses)


def test_deterministic() -> None:
    gen = torch.Generator().manual_seed(6)
    x = SE3().sample_uniform(300, generator=gen, dtype=torch.float64, bound=0.2)  # no real structure
    a, b = modes(x, SE3()), modes(x.clone(), SE3())
    for f in ("poses", "weights", "counts", "labels"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert a.dropped == b.dropped
    # every sample is labelled, weights are the cluster fractions
    assert torch.all(a.labels >= 0)
    assert torch.equal(torch.bincount(a.labels), a.counts)
    assert_close(a.weights.sum(), torch.tensor(1.0, dtype=torch.float64))
    SE3().check(a.poses)


def test_batched_input() -> None:
    gen = torch.Generator().manual_seed(7)
    c = SO3().sample_uniform(1, generator=gen, dtype=torch.float64)
    x1, _ = noisy(SO3(), c, [100], [DEG] * 3, gen)
    x2, _ = noisy(SO3(), separated_rotations(2, 60.0, gen), [60, 40], [DEG] * 3, gen)
    out = modes(torch.stack([x1, x2]), SO3())
    assert isinstance(out, list) and [len(m) for m in out] == [1, 2]
    assert torch.equal(out[1].labels, modes(x2, SO3()).labels)


def test_se2() -> None:
    gen = torch.Generator().manual_seed(8)
    c = SE2().exp(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64))
    x, labels = noisy(SE2(), c, [50, 30, 20], [0.01, 0.01, DEG], gen)
    m = modes(x, SE2())
    assert m.counts.tolist() == [50, 30, 20]
    assert_close(m.poses, c, atol=0.02, rtol=0)


def test_empty_and_validation() -> None:
    m = modes(torch.zeros(0, 4, 4), SE3())
    assert len(m) == 0 and m.labels.shape == (0,)
    x = SO3().identity(3)
    with pytest.raises(ValueError, match="expected samples"):
        modes(x, SE3())
    with pytest.raises(TypeError):
        modes(x.long(), SO3())
    with pytest.raises(ValueError, match="radius_deg"):
        modes(x, SO3(), radius_deg=0.0)
    with pytest.raises(ValueError, match="max_modes"):
        modes(x, SO3(), max_modes=0)
    with pytest.raises(ValueError, match="min_weight"):
        modes(x, SO3(), min_weight=1.5)
