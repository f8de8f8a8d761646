"""The image-free denoiser (posediff.nn.MLPDenoiser): shapes, broadcasting, gradients, fitting.

Reference sizes: the default ``MLPDenoiser(512, 6, 6)`` (F = 128, hidden 256, time 256, one layer,
Fourier blocks) has 1,249,542 parameters:

    time_proj   Linear(256 → 256) + bias                     65,792
    pose_proj   Linear(6·256 = 1536 → 256), no bias         393,216
    cond block  cond_proj 512 → 512 (262,656) + 3 × 256²+b  460,032
    time block  cond_proj 256 → 512 (131,584) + 3 × 256²+b  328,960
    out         Linear(256 → 6) + bias                        1,542

``block="scale_bias"`` has the same count; ``MLPDenoiser(512, 3, 3)`` (SO(3)) has 1,052,163.
"""

import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.nn import ConditionedBlock, FourierBlock, MLPDenoiser, ScaleBiasBlock

BLOCKS = ["fourier", "scale_bias"]


def _inputs(
    b: int = 3, n: int = 5, in_dim: int = 6, cond_dim: int = 4, seed: int = 0
) -> tuple[Tensor, Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, n, in_dim, generator=g)
    noise = torch.randint(0, 100, (b, n), generator=g).float()
    cond = torch.randn(b, cond_dim, generator=g)
    return x, noise, cond


def _small(block: str = "fourier", **kwargs: object) -> MLPDenoiser:
    torch.manual_seed(0)
    opts: dict = {"hidden_dim": 32, "num_frequencies": 8, "time_dim": 16, "block": block} | kwargs
    return MLPDenoiser(4, 6, 5, **opts)


def test_default_parameter_count() -> None:
    count = sum(p.numel() for p in MLPDenoiser(512, 6, 6).parameters())
    assert count == 1_249_542
    assert sum(p.numel() for p in MLPDenoiser(512, 6, 6, block="scale_bias").parameters()) == count
    assert sum(p.numel() for p in MLPDenoiser(512, 3, 3).parameters()) == 1_052_163


@pytest.mark.parametrize("block", BLOCKS)
def test_output_shapes_3d_and_2d(block: str) -> None:
    net = _small(block)
    x, noise, cond = _inputs()
    assert net(x, noise, cond).shape == (3, 5, 5)
    assert net(x[0], noise[0], cond[:1].expand(5, 4)).shape == (5, 5)  # 2-D: (M, in_dim), (M,), (M, C)
    assert net(x[0], noise[0], cond[0]).shape == (5, 5)  # one condition for all M samples
    assert net(x[0, 0], noise[0, 0], cond[0]).shape == (5,)  # a single sample


@pytest.mark.parametrize("block", BLOCKS)
def test_condition_broadcasts_like_explicit_expansion(block: str) -> None:
    net = _small(block, num_layers=2)
    x, noise, cond = _inputs()
    broadcast = net(x, noise, cond)
    assert_close(broadcast, net(x, noise, cond[:, None, :].expand(3, 5, 4)))
    assert_close(broadcast, net(x, noise, cond[:, None, :]))
    # 2-D input, one row per sample, equals the 3-D call flattened
    flat = net(x.reshape(15, 6), noise.reshape(15), cond.repeat_interleave(5, dim=0))
    assert_close(flat, broadcast.reshape(15, 5))


def test_noise_forms() -> None:
    net = _small()
    x, noise, cond = _inputs()
    out = net(x, noise, cond)
    assert_close(net(x, noise[..., None], cond), out)  # (B, N, 1), as the reference feeds t
    assert_close(net(x, noise.long(), cond), out)  # an integer noise-level index
    level = torch.full((3, 1), 17.0)  # one level per condition, broadcast over N
    assert_close(net(x, level, cond), net(x, level.expand(3, 5), cond))
    assert_close(net(x, 17, cond), net(x, level.expand(3, 5), cond))
    with pytest.raises(ValueError, match="noise must have shape"):
        net(x, noise[0], cond)  # (N,) is ambiguous for (B, N) samples: rejected
    with pytest.raises(ValueError, match="noise must have shape"):
        net(x, torch.zeros(3, 4), cond)


def test_bad_condition_and_input_shapes() -> None:
    net = _small()
    x, noise, cond = _inputs()
    with pytest.raises(ValueError, match="cond_dim=4"):
        net(x, noise, cond[:, :3])
    with pytest.raises(ValueError, match="does not broadcast"):
        net(x, noise, torch.zeros(2, 4))
    with pytest.raises(ValueError, match="more leading dims"):
        net(x[0], noise[0], torch.zeros(5, 1, 4))
    with pytest.raises(ValueError, match="required"):
        net(x, noise)
    with pytest.raises(ValueError, match="in_dim=6"):
        net(x[..., :3], noise, cond)


def test_unconditional_denoiser() -> None:
    torch.manual_seed(0)
    net = MLPDenoiser(0, 3, 3, hidden_dim=16, num_frequencies=4, time_dim=8)
    assert len(net.cond_blocks) == 0 and len(net.time_blocks) == 1
    x = torch.randn(7, 3)
    assert net(x, torch.arange(7)).shape == (7, 3)
    with pytest.raises(ValueError, match="cond_dim=0"):
        net(x, torch.arange(7), torch.zeros(7, 1))


def test_blocks_are_selected_by_name() -> None:
    assert ConditionedBlock.lookup("fourier") is FourierBlock
    assert ConditionedBlock.lookup("scale_bias") is ScaleBiasBlock
    assert isinstance(_small("fourier").time_blocks[0], FourierBlock)
    net = _small("scale_bias", num_layers=3)
    assert all(isinstance(b, ScaleBiasBlock) for b in [*net.cond_blocks, *net.time_blocks])
    assert len(net.cond_blocks) == len(net.time_blocks) == 3


def test_unknown_block_name_lists_registered_names() -> None:
    with pytest.raises(KeyError) as err:
        ConditionedBlock.lookup("transformer")
    msg = str(err.value)
    assert msg == "unknown conditioned block 'transformer'; registered: fourier, scale_bias"
    with pytest.raises(KeyError, match="registered: fourier, scale_bias"):
        MLPDenoiser(4, 6, 6, block="film")


def test_gradients_reach_every_parameter() -> None:
    for block in BLOCKS:
        net = _small(block, num_layers=2)
        x, noise, cond = _inputs()
        x.requires_grad_(True)
        net(x, noise, cond).square().sum().backward()
        for name, p in net.named_parameters():
            assert p.grad is not None, f"{block}: no gradient for {name}"
            assert p.grad.abs().sum() > 0, f"{block}: zero gradient for {name}"
        assert x.grad is not None and torch.isfinite(x.grad).all()


def test_condition_projected_once_per_condition() -> None:
    """The condition block projects (B, 1, C), not the (B, N, C) expansion; once per forward."""
    net = _small(num_layers=2)
    x, noise, cond = _inputs(b=3, n=5)
    cond_shapes: list[tuple[int, ...]] = []
    time_shapes: list[tuple[int, ...]] = []
    hooks = [
        b.cond_proj.register_forward_hook(lambda m, i, o: cond_shapes.append(tuple(i[0].shape)))
        for b in net.cond_blocks
    ]
    hooks += [
        b.cond_proj.register_forward_hook(lambda m, i, o: time_shapes.append(tuple(i[0].shape)))
        for b in net.time_blocks
    ]
    try:
        net(x, noise, cond)
    finally:
        for h in hooks:
            h.remove()
    assert cond_shapes == [(3, 1, 4)] * 2  # one call per layer, leading dims B×1 (not B×N)
    assert time_shapes == [(3, 5, 16)] * 2  # the time embedding is per sample


def test_zero_init_output() -> None:
    net = _small(zero_init_output=True)
    x, noise, cond = _inputs()
    assert_close(net(x, noise, cond), torch.zeros(3, 5, 5))
    net.out.weight.data.fill_(1.0)
    net.reset_parameters()
    assert_close(net(x, noise, cond), torch.zeros(3, 5, 5))


def test_float64_and_determinism() -> None:
    x, noise, cond = _inputs()
    a = _small()(x, noise, cond)
    assert_close(_small()(x, noise, cond), a, rtol=0, atol=0)  # same seed, same net, same output
    out64 = _small().double()(x.double(), noise.double(), cond.double())
    assert out64.dtype == torch.float64
    assert_close(out64.float(), a)


@pytest.mark.parametrize("block", BLOCKS)
def test_fits_a_small_nonlinear_target(block: str) -> None:
    """~200 Adam steps on a fixed batch drive the MSE down by at least 10×."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(8, 16, 3, generator=g)
    noise = torch.randint(0, 100, (8, 16), generator=g).float()
    cond = torch.randn(8, 2, generator=g)
    c = cond[:, None, :]
    target = torch.stack(
        [
            torch.sin(2 * x[..., 0]) * c[..., 0],
            torch.cos(noise / 30) * x[..., 1] + c[..., 1],
            torch.tanh(x[..., 2] * c[..., 0] + x[..., 0]),
        ],
        dim=-1,
    )
    net = MLPDenoiser(2, 3, 3, hidden_dim=64, num_frequencies=32, time_dim=64, block=block)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(200):
        loss = (net(x, noise, cond) - target).square().mean()
        losses.append(loss.item())
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = (net(x, noise, cond) - target).square().mean().item()
    assert final < losses[0] / 10, f"{block}: loss {losses[0]:.3g} -> {final:.3g}"
