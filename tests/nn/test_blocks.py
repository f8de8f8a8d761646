"""Sinusoidal embedding, conditioned blocks (paper Eq. 13 and scale-bias) and their initialisation."""

import math

import pytest
import torch
from torch import Tensor, nn
from torch.testing import assert_close

from posediff.nn import (
    ACTIVATIONS,
    ConditionedBlock,
    FourierBlock,
    LecunLinear,
    MLPDenoiser,
    ScaleBiasBlock,
    SinusoidalEmbedding,
    make_activation,
)

# ---------------------------------------------------------------------------- embedding


@pytest.mark.parametrize("values", [[0.0, 1.0, -2.5], [99.0, 0.25, 3.0]])
def test_embedding_matches_hand_formula(values: list[float]) -> None:
    num_f, period = 5, 1e4
    emb = SinusoidalEmbedding(num_f, period)
    out = emb(torch.tensor(values, dtype=torch.float64))
    assert out.shape == (len(values) * 2 * num_f,) == (emb.out_features(len(values)),)
    expected = []
    for v in values:  # component-major: all sines of component i, then its cosines
        freqs = [period ** (-j / (num_f - 1)) for j in range(num_f)]
        expected += [math.sin(v * f) for f in freqs] + [math.cos(v * f) for f in freqs]
    assert_close(out, torch.tensor(expected, dtype=torch.float64))
    assert_close(emb(torch.tensor(values)), torch.tensor(expected, dtype=torch.float32))


def test_embedding_defaults_and_shapes() -> None:
    emb = SinusoidalEmbedding()
    freqs = emb.frequencies(dtype=torch.float64)
    assert freqs.shape == (128,)
    assert_close(freqs[[0, -1]], torch.tensor([1.0, 1e-4], dtype=torch.float64))
    assert emb(torch.zeros(2, 7, 6)).shape == (2, 7, 6 * 256)
    assert list(emb.parameters()) == [] and list(emb.buffers()) == []
    assert emb(torch.tensor([3])).dtype == torch.get_default_dtype()  # integer input
    one = SinusoidalEmbedding(1)
    assert_close(one(torch.tensor([2.0])), torch.tensor([math.sin(2.0), math.cos(2.0)]))
    with pytest.raises(ValueError):
        SinusoidalEmbedding(0)


def test_embedding_min_period_sets_the_fastest_frequency() -> None:
    emb = SinusoidalEmbedding(9, max_period=10.0, min_period=1 / 16)
    freqs = emb.frequencies(dtype=torch.float64)
    assert_close(freqs[[0, -1]], torch.tensor([16.0, 0.1], dtype=torch.float64))
    ratios = freqs[1:] / freqs[:-1]  # geometric
    assert_close(ratios, ratios[:1].expand_as(ratios))
    x = torch.tensor([0.3], dtype=torch.float64)
    assert_close(emb(x), torch.cat([(x * freqs).sin(), (x * freqs).cos()]))
    assert_close(
        SinusoidalEmbedding(1, min_period=0.5).frequencies(dtype=torch.float64),
        torch.tensor([2.0], dtype=torch.float64),
    )
    with pytest.raises(ValueError, match="min_period"):
        SinusoidalEmbedding(4, max_period=1.0, min_period=2.0)
    with pytest.raises(ValueError, match="min_period"):
        SinusoidalEmbedding(4, min_period=0.0)


def test_denoiser_pose_periods_apply_to_the_pose_only() -> None:
    net = MLPDenoiser(4, 3, 3, pose_min_period=0.0625, pose_max_period=10.0)
    assert_close(net.pose_embedding.frequencies()[[0, -1]], torch.tensor([16.0, 0.1]))
    assert_close(net.embedding.frequencies()[[0, -1]], torch.tensor([1.0, 1e-4]))  # noise level: reference
    assert "pose_periods=(0.0625, 10)" in repr(net)
    assert net(torch.randn(2, 5, 3), torch.tensor(3.0), torch.randn(2, 4)).shape == (2, 5, 3)


# ---------------------------------------------------------------------------- blocks


def _block(kind: type[ConditionedBlock], activation: str = "leaky_relu") -> ConditionedBlock:
    torch.manual_seed(0)
    return kind(8, 3, activation)


def _ac(block: ConditionedBlock, c: Tensor) -> tuple[Tensor, Tensor]:
    proj = block.cond_proj(torch.nn.functional.silu(c))
    return proj[..., :8], proj[..., 8:]


def test_fourier_block_is_eq13() -> None:
    """f_i(x, c) = Σ_j W_ij (A_j(c) cos(π x_j) + B_j(c) sin(π x_j)), x = Linear(act(h)), + skip."""
    block = _block(FourierBlock)
    g = torch.Generator().manual_seed(2)
    h, c = torch.randn(4, 8, generator=g), torch.randn(4, 3, generator=g)
    a, b = _ac(block, c)
    x = block.inner(nn.functional.leaky_relu(h, 0.01))
    w, w0 = block.outer.weight, block.outer.bias
    f = torch.einsum("ij,nj->ni", w, a * torch.cos(math.pi * x) + b * torch.sin(math.pi * x)) + w0
    assert_close(block(h, c), f + block.skip(h))


def test_scale_bias_block_is_film() -> None:
    block = _block(ScaleBiasBlock, activation="silu")
    g = torch.Generator().manual_seed(3)
    h, c = torch.randn(4, 8, generator=g), torch.randn(4, 3, generator=g)
    a, b = _ac(block, c)
    u = block.inner(nn.functional.silu(h)) * (1 + a) + b
    assert_close(block(h, c), block.outer(nn.functional.silu(u)) + block.skip(h))


@pytest.mark.parametrize("kind", [FourierBlock, ScaleBiasBlock])
def test_block_projected_condition_and_broadcasting(kind: type[ConditionedBlock]) -> None:
    block = _block(kind)
    g = torch.Generator().manual_seed(4)
    h, c = torch.randn(2, 6, 8, generator=g), torch.randn(2, 1, 3, generator=g)
    out = block(h, c)
    assert out.shape == (2, 6, 8)
    projected = block.condition(c)
    assert projected.shape == (2, 1, 16)
    assert_close(block(h, projected=projected), out)
    assert_close(block(h, c.expand(2, 6, 3)), out)
    with pytest.raises(ValueError, match="exactly one"):
        block(h)
    with pytest.raises(ValueError, match="exactly one"):
        block(h, c, projected=projected)
    with pytest.raises(ValueError, match="cond_dim=3"):
        block(h, c[..., :2])
    with pytest.raises(ValueError, match="dim=8"):
        block(h[..., :4], c)


def test_activations_by_name() -> None:
    assert set(ACTIVATIONS) == {"leaky_relu", "silu", "relu", "gelu", "sin"}
    x = torch.linspace(-2, 2, 9)
    assert_close(make_activation("leaky_relu")(x), torch.where(x > 0, x, 0.01 * x))
    assert_close(make_activation("sin")(x), torch.sin(x))
    for name in ACTIVATIONS:
        assert _block(FourierBlock, name)(torch.randn(2, 8), torch.randn(2, 3)).shape == (2, 8)
    with pytest.raises(ValueError, match="gelu, leaky_relu, relu, silu, sin"):
        make_activation("tanh")
    with pytest.raises(ValueError, match="unknown activation 'tanh'"):
        MLPDenoiser(2, 3, 3, activation="tanh")


def test_new_block_registers_and_plugs_in() -> None:
    """Registered's __init_subclass__ composes with nn.Module: a subclass is a working module."""

    class Gated(ConditionedBlock, name="gated_test"):
        def __init__(self, dim: int, cond_dim: int, activation: str = "leaky_relu") -> None:
            super().__init__(dim, cond_dim, activation)
            self.lin = nn.Linear(dim, dim)

        def modulate(self, h: Tensor, a: Tensor, b: Tensor) -> Tensor:
            return self.lin(h) * torch.sigmoid(a) + b

    try:
        assert ConditionedBlock.lookup("gated_test") is Gated and Gated.name == "gated_test"
        net = MLPDenoiser(2, 3, 3, hidden_dim=8, num_frequencies=4, time_dim=4, block="gated_test")
        assert net(torch.randn(5, 3), torch.arange(5), torch.randn(5, 2)).shape == (5, 3)
        assert any(k.startswith("time_blocks.0.lin.") for k in net.state_dict())
    finally:
        ConditionedBlock._entries.pop("gated_test", None)
    with pytest.raises(NotImplementedError):

        class Plain(ConditionedBlock):  # unnamed: not registered, modulate missing
            pass

        Plain(4, 2)(torch.zeros(4), torch.zeros(2))
    assert sorted(ConditionedBlock.registry) == ["fourier", "scale_bias"]


def test_lecun_init() -> None:
    torch.manual_seed(0)
    lin = LecunLinear(400, 300)
    std = lin.weight.std().item()
    assert abs(std - 400**-0.5) < 0.03 * 400**-0.5  # variance 1 / fan_in (after truncation)
    assert lin.weight.abs().max() <= 2 * 400**-0.5 / 0.87962566103423978 + 1e-6
    assert torch.count_nonzero(lin.bias) == 0
