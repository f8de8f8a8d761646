"""The anchored denoiser: exactly the paper's network when the anchor is the identity, the paper's network
on X̂⁻¹X̃ otherwise; the anchor travels inside the one condition tensor; the auxiliary loss trains it."""

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import ConcentratedGaussian, Diffusion, FewStepSampler, PowerSchedule
from posediff.lie import get_group
from posediff.models import PoseDiffusionModule
from posediff.nn import Encoding, MLPDenoiser
from posediff.testing import synthetic_batch

pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")


class FixedPoseEncoder(torch.nn.Module):
    """A stand-in encoder: a learned feature and a given anchor (so the test controls X̂)."""

    def __init__(self, anchor: torch.Tensor, dim: int = 8) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(3, dim)
        self.anchor = anchor

    def forward(self, image: torch.Tensor) -> Encoding:
        f = self.lin(image.mean((-2, -1)))
        t = self.anchor[..., :3, 3] if self.anchor.shape[-1] == 4 else None
        return Encoding(
            f, self.anchor[..., :3, :3].expand(len(f), 3, 3), None if t is None else t.expand(len(f), 3)
        )


def _modules(group: str, anchor: torch.Tensor) -> tuple[PoseDiffusionModule, PoseDiffusionModule]:
    g = get_group(group)
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    torch.manual_seed(0)
    denoiser = MLPDenoiser(8, g.dim, g.dim, hidden_dim=32, num_frequencies=8, time_dim=16)
    enc = FixedPoseEncoder(anchor)
    anchored = PoseDiffusionModule(diffusion, denoiser, FewStepSampler, encoder=enc, anchor=True, num_noisy=4)
    paper = PoseDiffusionModule(
        diffusion, denoiser, FewStepSampler, encoder=torch.nn.Sequential(), num_noisy=4
    )
    return anchored, paper


@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
def test_identity_anchor_is_the_papers_network(group: str) -> None:
    g = get_group(group)
    anchored, paper = _modules(group, g.identity(()))
    batch = synthetic_batch(3, 8, group)
    cond = anchored.encode(batch["image"])
    feature = anchored.encode_full(batch["image"]).feature
    x = g.sample_uniform((3, 5), generator=torch.Generator().manual_seed(1))
    sigma = torch.full((3, 5), 0.3)
    assert cond.shape == (3, 8 + g.matrix_dim**2)
    assert_close(anchored(x, sigma, cond), paper(x, sigma, feature))


@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
def test_anchor_makes_the_input_relative(group: str) -> None:
    g = get_group(group)
    X = g.sample_uniform((), generator=torch.Generator().manual_seed(2))
    anchored, paper = _modules(group, X)
    batch = synthetic_batch(2, 8, group)
    cond = anchored.encode(batch["image"])
    feature, anchor = anchored.unpack(cond)
    assert_close(anchor, X.expand(2, *X.shape))
    x = g.sample_uniform((2, 4), generator=torch.Generator().manual_seed(3))
    sigma = torch.full((2, 4), 0.2)
    rel = g.compose(g.inverse(X), x)
    assert_close(anchored(x, sigma, cond), paper(rel, sigma, feature), atol=1e-5, rtol=1e-5)
    # the samplers carry the packed condition untouched
    out = anchored.sample(batch["image"], 3, 2, generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, 3, g.matrix_dim, g.matrix_dim)


def test_anchor_needs_an_encoder_that_estimates_a_pose() -> None:
    g = get_group("se3")
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    m = PoseDiffusionModule(diffusion, MLPDenoiser(3, 6, 6, hidden_dim=8, num_frequencies=4, time_dim=8), FewStepSampler,
                            encoder=torch.nn.Linear(3, 3), anchor=True)  # fmt: skip
    with pytest.raises(ValueError, match="needs an encoder that estimates a pose"):
        m.encode(torch.zeros(1, 3))


def test_auxiliary_loss_is_added_and_trains_the_anchor() -> None:
    from posediff.nn import PoseEncoder

    g = get_group("se3")
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    batch = synthetic_batch(4, 32, "se3")
    losses = {}
    for w in (0.0, 1.0):
        torch.manual_seed(0)
        enc = PoseEncoder(image_size=32, out_dim=8)
        den = MLPDenoiser(8, 6, 6, hidden_dim=16, num_frequencies=4, time_dim=8)
        m = PoseDiffusionModule(
            diffusion,
            den,
            FewStepSampler,
            encoder=enc,
            anchor=True,
            aux_weight=w,
            num_noisy=4,
            cond_key="image",
        )
        torch.manual_seed(1)
        losses[w] = float(m.training_step(batch, 0))
        enc_out = m.encode_full(batch["image"], pose=batch["pose"])
        aux = m.side_losses(batch, enc_out, "train")
        if w == 0.0:
            assert float(aux) == 0.0
        else:
            assert float(aux) > 0.0
            aux.backward()
            assert enc.pose_head.weight.grad.abs().sum() > 0
    assert losses[1.0] > losses[0.0]


def test_invariant_head_anchor_needs_the_auxiliary_loss() -> None:
    from posediff.nn import PoseEncoder

    g = get_group("se3")
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    enc = PoseEncoder(image_size=32, out_dim=8, rotation_head="invariant")
    den = MLPDenoiser(8, 6, 6, hidden_dim=8, num_frequencies=4, time_dim=8)
    with pytest.raises(ValueError, match="aux_weight > 0"):
        PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc, anchor=True)
    m = PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc, anchor=True, aux_weight=1.0)
    assert enc.decode_in_training
    PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc)  # the paper's input: a linear probe
    assert not enc.decode_in_training and m.anchor
