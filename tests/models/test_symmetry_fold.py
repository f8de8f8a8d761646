"""The symmetry-folded denoiser: the nearest symmetry is exact, the folded network's score transforms
as the score of a symmetric density must (``s(X·S) = Ad(S)⁻¹ s(X)``), every sample lands where the
unfolded network would put it for the one mode, and a model without a shape classifier is refused."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.diffusion import ConcentratedGaussian, Diffusion, FewStepSampler, PowerSchedule
from posediff.lie import get_group
from posediff.lie._pose import make_pose
from posediff.models import PoseDiffusionModule
from posediff.nn import Encoding, MLPDenoiser
from posediff.symmetry import SHAPES, nearest_symmetry, symmetry_group, symsol_nearest_symmetry

pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")


def _traces(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    return torch.einsum("bij,sji->bs", M, G)


@pytest.mark.parametrize("shape", SHAPES)
def test_nearest_symmetry_is_the_best_element(shape: str) -> None:
    g = get_group("so3")
    M = g.sample_uniform((500,), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    S = nearest_symmetry(shape, M)
    trace = (M @ S).diagonal(dim1=-2, dim2=-1).sum(-1)
    # the continuous groups on a 0.25° grid: the closed form is at least as good as every grid element
    G = symmetry_group(shape, dtype=torch.float64, **({"step_deg": 0.25} if shape in ("cone", "cyl") else {}))
    best = _traces(M, G).amax(-1)
    assert (trace >= best - 1e-9).all()
    assert (trace <= best + 1e-5).all()  # and within the grid's resolution of it
    assert_close(S.mT @ S, torch.eye(3, dtype=torch.float64).expand_as(S))
    assert_close(torch.linalg.det(S), torch.ones(500, dtype=torch.float64))
    if shape not in ("cone", "cyl"):  # a member of the exact group
        d = (S[:, None] - G[None]).abs().flatten(-2).amax(-1).amin(-1)
        assert float(d.max()) < 1e-12
    else:  # the z axis kept (cone: Rz only) or flipped (cylinder)
        assert_close(S[:, 2, 2].abs(), torch.ones(500, dtype=torch.float64))
        if shape == "cone":
            assert_close(S[:, 2, 2], torch.ones(500, dtype=torch.float64))


def test_mixed_shapes_select_each_ones_answer() -> None:
    g = get_group("so3")
    M = g.sample_uniform((10, 3), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ids = torch.tensor([0, 1, 2, 3, 4, 4, 3, 2, 1, 0])
    S = symsol_nearest_symmetry(ids, M)
    for i, k in enumerate(ids.tolist()):
        assert_close(S[i], nearest_symmetry(SHAPES[k], M[i]))


class ShapePoseEncoder(torch.nn.Module):
    """A stand-in for the invariant head: a learned feature, a given anchor and a given shape."""

    rotation_head = "invariant"
    shapes = SHAPES

    def __init__(self, anchor: torch.Tensor, shape: str, dim: int = 8) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(3, dim)
        self.anchor = anchor
        self.shape = shape

    def forward(self, image: torch.Tensor) -> Encoding:
        f = self.lin(image.mean((-2, -1)))
        n = len(f)
        t = self.anchor[..., :3, 3].expand(n, 3) if self.anchor.shape[-1] == 4 else None
        logits = torch.full((n, len(SHAPES)), -5.0)
        logits[:, SHAPES.index(self.shape)] = 5.0
        return Encoding(f, self.anchor[..., :3, :3].expand(n, 3, 3), t, shape_logits=logits)


def _module(group: str, anchor: torch.Tensor, shape: str, fold: bool = True) -> PoseDiffusionModule:
    g = get_group(group)
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    torch.manual_seed(0)
    denoiser = MLPDenoiser(8, g.dim, g.dim, hidden_dim=32, num_frequencies=8, time_dim=16)
    return PoseDiffusionModule(
        diffusion, denoiser, FewStepSampler, encoder=ShapePoseEncoder(anchor, shape), anchor=True,
        aux_weight=1.0, symmetry_fold=fold, num_noisy=4,
    )  # fmt: skip


def _rz(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
@pytest.mark.parametrize("shape", ["tet", "icosa", "cyl"])
def test_folded_score_is_equivariant(group: str, shape: str) -> None:
    """``out(X·S) = Ad(S)⁻¹ out(X)`` for every symmetry S: the score of a density with p(X·S) = p(X)."""
    g = get_group(group)
    gen = torch.Generator().manual_seed(3)
    X_hat = g.sample_uniform((), generator=gen)
    m = _module(group, X_hat, shape)
    cond = m.encode(torch.rand(2, 3, 8, 8, generator=gen))
    assert cond.shape == (2, 8 + g.matrix_dim**2 + 1)
    assert_close(m.folded_shapes(cond), torch.full((2,), SHAPES.index(shape)))
    x = g.sample_uniform((2, 6), generator=gen)
    sigma = torch.full((2, 6), 0.3)
    out = m(x, sigma, cond)
    syms = (
        symmetry_group(shape, dtype=torch.float32)[1:4]
        if shape != "cyl"
        else torch.stack([_rz(0.7), torch.diag(torch.tensor([1.0, -1, -1])) @ _rz(2.1)])
    )
    for S in syms:
        Sx = S if g.matrix_dim == 3 else make_pose(S, torch.zeros(3))
        moved = m(g.compose(x, Sx.expand_as(x)), sigma, cond)
        back = (torch.linalg.inv(g.adjoint(Sx)) @ out.unsqueeze(-1)).squeeze(-1)
        assert_close(moved, back, atol=2e-4, rtol=2e-4)


@pytest.mark.parametrize("group", ["so3", "r3so3"])
def test_fold_is_the_plain_anchor_inside_the_anchors_domain(group: str) -> None:
    """Near the anchor (closer than half the smallest angle between equivalents) nothing is folded."""
    g = get_group(group)
    gen = torch.Generator().manual_seed(4)
    X_hat = g.sample_uniform((), generator=gen)
    folded, plain = _module(group, X_hat, "icosa"), _module(group, X_hat, "icosa", fold=False)
    plain.load_state_dict(folded.state_dict())
    img = torch.rand(2, 3, 8, 8, generator=gen)
    cond_f, cond_p = folded.encode(img), plain.encode(img)
    z = 0.15 * torch.randn(2, 5, g.dim, generator=gen)  # |φ| well below 18° (icosahedral: 36° apart)
    x = g.compose(X_hat.expand(2, 5, *X_hat.shape), g.exp(z))
    sigma = torch.full((2, 5), 0.1)
    assert_close(folded(x, sigma, cond_f), plain(x, sigma, cond_p))


def test_samples_and_training_step_run() -> None:
    from posediff.testing import synthetic_batch

    g = get_group("r3so3")
    m = _module("r3so3", g.identity(()), "cube")
    batch = synthetic_batch(3, 8, "r3so3")
    batch["shape"] = torch.tensor([1, 1, 1])
    out = m.sample(batch["image"], 4, 2, generator=torch.Generator().manual_seed(0))
    assert out.shape == (3, 4, 4, 4) and torch.isfinite(out).all()
    m.cond_key = "image"
    loss = m.training_step(batch, 0)
    assert torch.isfinite(loss)


def test_fold_needs_the_anchor_and_a_shape_classifier() -> None:
    g = get_group("so3")
    diffusion = Diffusion(ConcentratedGaussian(g), PowerSchedule())
    den = MLPDenoiser(8, 3, 3, hidden_dim=8, num_frequencies=4, time_dim=8)
    enc = ShapePoseEncoder(g.identity(()), "tet")
    with pytest.raises(ValueError, match="symmetry_fold=true needs module.anchor=true"):
        PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc, anchor=False, symmetry_fold=True)
    enc.rotation_head = "6d"
    with pytest.raises(ValueError, match="invariant head's shape classifier"):
        PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc, anchor=True, symmetry_fold=True)
    with pytest.raises(ValueError, match="symmetry_fold must be true or false"):
        PoseDiffusionModule(diffusion, den, FewStepSampler, encoder=enc, anchor=True, symmetry_fold="yes")
