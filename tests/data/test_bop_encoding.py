"""RoI crops and the network's pose encoding for BOP crops: exact inverses, against float64 oracles."""

import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from posediff.data.bop.encoding import PoseEncoding, allocentric_rotation
from posediff.data.bop.roi import clip_box, crop, crop_intrinsics, crop_matrix, dzi
from posediff.lie import SO3

K_TLESS = np.array([[1075.65, 0.0, 373.06], [0.0, 1073.90, 257.73], [0.0, 0.0, 1.0]])


def _random_poses(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    R = SO3().exp(torch.randn(n, 3, generator=gen, dtype=torch.float64) * 2.0)
    t = torch.stack(
        [
            torch.empty(n, dtype=torch.float64).uniform_(-200, 200, generator=gen),
            torch.empty(n, dtype=torch.float64).uniform_(-150, 150, generator=gen),
            torch.empty(n, dtype=torch.float64).uniform_(400, 1200, generator=gen),
        ],
        -1,
    )
    return R, t


def test_allocentric_rotation_takes_the_ray_to_the_optical_axis(generator: torch.Generator) -> None:
    _, t = _random_poses(64, generator)
    t = torch.cat([t, torch.tensor([[0.0, 0.0, 700.0], [1e-9, 0.0, 500.0]], dtype=torch.float64)])
    Q = allocentric_rotation(t)
    z = (Q @ (t / t.norm(dim=-1, keepdim=True))[..., None])[..., 0]
    assert_close(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(z), atol=1e-12, rtol=0)
    assert_close(Q @ Q.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(Q), atol=1e-12, rtol=0)
    assert_close(torch.linalg.det(Q), torch.ones(len(t), dtype=torch.float64))
    # on the optical axis it is the identity; the angle equals the ray's angle to the axis
    assert_close(Q[-2], torch.eye(3, dtype=torch.float64))
    angle = torch.arccos(((Q.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    assert_close(angle, torch.arccos(t[:, 2] / t.norm(dim=-1)), atol=1e-7, rtol=0)


def test_crop_intrinsics_match_the_crop_of_the_image() -> None:
    centre, side, out = np.array([300.5, 210.0]), 151.0, 224
    Kc = crop_intrinsics(K_TLESS, centre, side, out)
    M = crop_matrix(centre, side, out)
    X = np.array([[10.0, -20.0, 700.0], [-50.0, 30.0, 650.0]])
    p = X @ K_TLESS.T
    uv = p[:, :2] / p[:, 2:]
    pc = X @ Kc.T
    assert_close(torch.from_numpy(pc[:, :2] / pc[:, 2:]), torch.from_numpy(uv @ M[:, :2].T + M[:, 2]))
    # the crop's centre pixel is the box centre; focal scaled by the zoom
    assert_close(
        torch.from_numpy(M @ np.array([*centre, 1.0])), torch.full((2,), (out - 1) / 2, dtype=torch.float64)
    )
    assert Kc[0, 0] == pytest.approx(K_TLESS[0, 0] * out / side)


def test_crop_resamples_the_pixels_it_says() -> None:
    img = np.zeros((240, 320), dtype=np.uint8)
    img[100:120, 150:170] = 255  # a 20 px square centred at (159.5, 109.5)
    out = crop(img, np.array([159.5, 109.5]), 40.0, 80)
    ys, xs = np.nonzero(out > 127)
    assert (xs.mean(), ys.mean()) == pytest.approx((39.5, 39.5), abs=0.6)
    assert out.shape == (80, 80) and (out > 127).sum() == pytest.approx(40 * 40, rel=0.1)
    mask = crop(img > 0, np.array([159.5, 109.5]), 40.0, 80, nearest=True)
    assert mask.dtype == bool and mask.sum() == pytest.approx(1600, rel=0.1)
    # outside the image: black
    assert crop(img, np.array([-500.0, -500.0]), 40.0, 8).max() == 0


def test_dzi_ranges_and_test_box() -> None:
    bbox = np.array([100.0, 50.0, 60.0, 40.0])
    centre, side = dzi(bbox, (540, 720))
    assert_close(torch.from_numpy(centre), torch.tensor([130.0, 70.0], dtype=torch.float64))
    assert side == pytest.approx(90.0)
    rng = np.random.default_rng(0)
    draws = [dzi(bbox, (540, 720), rng=rng) for _ in range(2000)]
    cs = np.stack([c for c, _ in draws])
    ss = np.array([s for _, s in draws])
    assert np.all(np.abs(cs[:, 0] - 130) <= 0.25 * 60 + 1e-9) and np.all(
        np.abs(cs[:, 1] - 70) <= 0.25 * 40 + 1e-9
    )
    assert ss.min() >= 1.125 * 60 - 1e-9 and ss.max() <= 1.875 * 60 + 1e-9
    assert ss.min() < 1.15 * 60 and ss.max() > 1.85 * 60  # the whole range is used
    assert dzi(np.array([0, 0, 700.0, 500.0]), (540, 720))[1] == 720.0  # clipped to the image
    assert_close(torch.from_numpy(clip_box(np.array([-10.0, 500.0, 50.0, 100.0]), (540, 720))),
                 torch.tensor([0.0, 500.0, 40.0, 40.0], dtype=torch.float64))  # fmt: skip


@pytest.mark.parametrize("rotation", ["allocentric", "egocentric"])
def test_encoding_round_trip(rotation: str, generator: torch.Generator) -> None:
    R, t = _random_poses(256, generator)
    K = torch.from_numpy(K_TLESS).expand(256, 3, 3)
    p = (K @ t[..., None])[..., 0]
    o = p[:, :2] / p[:, 2:]
    centre = o + torch.randn(256, 2, generator=generator, dtype=torch.float64) * 10
    side = torch.empty(256, dtype=torch.float64).uniform_(60, 200, generator=generator)
    enc = PoseEncoding(rotation)
    enc.fit_stats(PoseEncoding.raw_translation(t, K, centre, side, 224))
    R_net, delta = enc.encode(R, t, K, centre, side, 224)
    # standardised: zero mean, unit std over the set the statistics came from
    assert_close(delta.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-9, rtol=0)
    assert_close(delta.std(0), torch.ones(3, dtype=torch.float64))
    R2, t2 = enc.decode(R_net, delta, K, centre, side, 224)
    assert_close(t2, t, atol=1e-9, rtol=1e-12)
    assert_close(R2, R, atol=1e-12, rtol=0)
    if rotation == "egocentric":
        assert_close(R_net, R)
    # broadcasting as the evaluation uses it: (B, N) samples against (B, 1) crops
    R3, t3 = enc.decode(
        R_net[:, None].expand(256, 5, 3, 3),
        delta[:, None].expand(256, 5, 3),
        K[:, None],
        centre[:, None],
        side[:, None],
        224,
    )
    assert_close(t3, t[:, None].expand(256, 5, 3), atol=1e-9, rtol=1e-12)
    assert_close(R3[:, 3], R, atol=1e-12, rtol=0)


def test_encoding_translation_meaning() -> None:
    """δ_xy is the projected centre's offset from the crop centre over the crop side; δ_z the depth at
    the crop's zoom."""
    K = torch.from_numpy(K_TLESS)
    t = torch.tensor([0.0, 0.0, 600.0], dtype=torch.float64)
    centre = torch.tensor([373.06 - 20.0, 257.73], dtype=torch.float64)
    raw = PoseEncoding.raw_translation(t, K, centre, torch.tensor(100.0, dtype=torch.float64), 224)
    assert_close(raw, torch.tensor([0.2, 0.0, 600.0 * 100 / 224], dtype=torch.float64))


def test_allocentric_is_invariant_to_where_the_object_is(generator: torch.Generator) -> None:
    """An object moved across the image and turned so that it faces the camera alike has one
    allocentric rotation."""
    R, _ = _random_poses(1, generator)
    t0 = torch.tensor([[0.0, 0.0, 700.0]], dtype=torch.float64)
    t1 = torch.tensor([[200.0, -100.0, 700.0]], dtype=torch.float64)
    R1 = allocentric_rotation(t1).transpose(-1, -2) @ R  # the same view from a ray off the axis
    enc = PoseEncoding("allocentric", [0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    K = torch.from_numpy(K_TLESS)[None]
    c, s = torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    assert_close(enc.encode(R, t0, K, c, s, 224)[0], enc.encode(R1, t1, K, c, s, 224)[0])


def test_encoding_refuses_bad_settings() -> None:
    with pytest.raises(ValueError, match="allocentric, egocentric"):
        PoseEncoding("sideways")
    with pytest.raises(ValueError, match="both"):
        PoseEncoding("allocentric", [0, 0, 0], None)
    with pytest.raises(ValueError, match="positive"):
        PoseEncoding("allocentric", [0, 0, 0], [1, 0, 1])
    with pytest.raises(RuntimeError, match="fit_stats"):
        PoseEncoding().stats()
    assert math.isfinite(PoseEncoding("egocentric", [0, 0, 1], [1, 1, 1]).stats()["mean"][2])


@pytest.mark.parametrize("rotation", ["allocentric", "egocentric"])
def test_decode_pose_of_full_and_rotation_only_poses(rotation: str, generator: torch.Generator) -> None:
    R, t = _random_poses(8, generator)
    K = torch.from_numpy(K_TLESS).expand(8, 3, 3)
    centre, side = (
        torch.full((8, 2), 300.0, dtype=torch.float64),
        torch.full((8,), 120.0, dtype=torch.float64),
    )
    enc = PoseEncoding(rotation, [0.0, 0.0, 300.0], [0.1, 0.1, 100.0])
    R_net, delta = enc.encode(R, t, K, centre, side, 224)
    x = torch.eye(4, dtype=torch.float64).repeat(8, 1, 1)
    x[:, :3, :3], x[:, :3, 3] = R_net, delta
    R4, t4 = enc.decode_pose(x, K, centre, side, 224)
    R3, t3 = enc.decode_pose(R_net, K, centre, side, 224, translation=t)
    assert_close(R4, R, atol=1e-12, rtol=0)
    assert_close(t4, t, atol=1e-9, rtol=1e-12)
    assert_close(R3, R, atol=1e-12, rtol=0)
    assert t3 is t
    with pytest.raises(ValueError, match="given translation"):
        enc.decode_pose(R_net, K, centre, side, 224)
