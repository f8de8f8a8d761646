"""log_likelihood by the probability-flow ODE, checked against an exact mixture-of-point-masses score."""

import math

import pytest
import torch

from posediff.diffusion import ConcentratedGaussian, Diffusion, LinearSchedule, MixtureOracle, log_likelihood
from posediff.lie import SE3, SO3
from posediff.symmetry import symmetry_group


def _setup(group, prior: str = "haar"):  # noqa: ANN001, ANN202
    d = Diffusion(ConcentratedGaussian(group), LinearSchedule(), prior=prior)
    r0 = group.sample_uniform((1,), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sym = symmetry_group("tet")
    if group.matrix_dim == 4:
        s4 = torch.eye(4, dtype=torch.float64).repeat(len(sym), 1, 1)
        s4[:, :3, :3] = sym
        sym = s4
    modes = r0 @ sym
    return d, modes, MixtureOracle(d, modes)


def test_equivalent_poses_equal_and_off_support_far_lower() -> None:
    g = SO3()
    d, modes, oracle = _setup(g)
    off = g.rplus(modes[:2], torch.tensor([[0.3, 0.0, 0.0], [0.0, 0.05, 0.0]], dtype=torch.float64))
    ll = log_likelihood(oracle, d, torch.cat([modes, off])[None], num_steps=20)[0]
    at_modes = ll[:12]
    assert float(at_modes.max() - at_modes.min()) < 1e-3, "the 12 equivalent poses must score the same"
    # exact: log(1/12) + log N(0; σ_min² I₃) (Haar normalised to Lebesgue at the identity)
    exact = -math.log(12) - 1.5 * math.log(2 * math.pi) - 3 * math.log(1e-4)
    assert abs(float(at_modes.mean()) - exact) < 0.5, f"{float(at_modes.mean()):.3f} vs exact {exact:.3f}"
    assert float(ll[12:].max()) < float(at_modes.min()) - 20, "off-support poses must be far less likely"


def test_se3_equivalents_and_translation_shift() -> None:
    g = SE3()
    d, modes, oracle = _setup(g)
    shifted = modes[:1].clone()
    shifted[:, :3, 3] += 0.05
    ll = log_likelihood(oracle, d, torch.cat([modes[:4], shifted])[None], num_steps=20)[0]
    assert float(ll[:4].max() - ll[:4].min()) < 1e-3
    assert float(ll[4]) < float(ll[:4].min()) - 20


def test_ranks_match_the_exact_density_at_moderate_noise() -> None:
    """Poses a few σ_min off a mode: the ODE value tracks the exact log density of p_{σ_min}."""
    g = SO3()
    d, modes, oracle = _setup(g)
    eps = torch.tensor([[1e-4, 0.0, 0.0], [2e-4, 0.0, 0.0], [0.0, 3e-4, 0.0]], dtype=torch.float64)
    x = g.rplus(modes[:3], eps)
    ll = log_likelihood(oracle, d, x[None], num_steps=40)[0]
    exact = (
        -math.log(12)
        - 1.5 * math.log(2 * math.pi)
        - 3 * math.log(1e-4)
        - 0.5 * (eps.norm(dim=-1) / 1e-4) ** 2
    )
    torch.testing.assert_close(ll, exact, rtol=0, atol=0.5)


def test_bad_steps() -> None:
    d, modes, oracle = _setup(SO3())
    with pytest.raises(ValueError, match="num_steps"):
        log_likelihood(oracle, d, modes[None, :1], num_steps=0)
