"""PoseEncoder: the 6-D rotation, the ray rotation, the crop geometry, the locator, shapes and gradients."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.data.symsol.render import SCENE_DISTANCE, intrinsics
from posediff.nn import Encoding, PoseEncoder, ray_rotation, rotation_from_6d


def test_rotation_from_6d_is_a_rotation_and_keeps_rotations() -> None:
    x = torch.randn(100, 6, dtype=torch.float64)
    R = rotation_from_6d(x)
    assert_close(R.mT @ R, torch.eye(3, dtype=torch.float64).expand(100, 3, 3), atol=1e-12, rtol=0)
    assert_close(torch.linalg.det(R), torch.ones(100, dtype=torch.float64))
    # a rotation's first two columns give that rotation back
    Q = rotation_from_6d(torch.randn(10, 6, dtype=torch.float64))
    assert_close(rotation_from_6d(torch.cat([Q[..., 0], Q[..., 1]], -1)), Q)


def test_ray_rotation_turns_the_optical_axis_onto_the_ray() -> None:
    t = torch.randn(50, 3, dtype=torch.float64)
    t[:, 2] = t[:, 2].abs() + 1.0
    R = ray_rotation(t)
    assert_close(R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), t / t.norm(dim=-1, keepdim=True))
    assert_close(R.mT @ R, torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12, rtol=0)
    assert_close(ray_rotation(torch.tensor([[0.0, 0.0, 5.0]])), torch.eye(3)[None])


def test_crop_is_centred_on_the_projection_of_the_translation() -> None:
    """A bright dot drawn where K projects t lands in the middle of the crop, at every place in view."""
    size, crop = 128, 32
    enc = PoseEncoder(image_size=size, crop_size=crop, out_dim=8).eval()
    K = intrinsics(size)
    t = torch.tensor([[0.0, 0.0, 0.0], [0.9, -0.7, 0.5], [-1.0, 1.0, -1.0]])
    img = torch.zeros(len(t), 3, size, size)
    for i, ti in enumerate(t):
        p = ti.double() + torch.tensor([0.0, 0.0, SCENE_DISTANCE], dtype=torch.float64)
        u, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
        img[i, :, int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2] = 1.0  # pixel (u, v) spans [u, u+1)
    out, ray = enc.crop(img, t)
    assert out.shape == (3, 3, crop, crop)
    for i in range(len(t)):
        m = out[i, 0]
        ys, xs = torch.meshgrid(torch.arange(crop) + 0.5, torch.arange(crop) + 0.5, indexing="ij")
        cy, cx = (m * ys).sum() / m.sum(), (m * xs).sum() / m.sum()
        assert abs(float(cx) - crop / 2) < 1.0 and abs(float(cy) - crop / 2) < 1.0
    # the crop side covers the object sphere: 2 f r / z pixels
    sides = enc.project(t)[0]
    (
        assert_close(sides[:, 2] - sides[:, 0], (sides[:1, 2] - sides[:1, 0]).expand(3)),
        "one crop scale at every depth",
    )
    boxes, _ = enc.project(t[:1])
    assert math.isclose(
        float(boxes[0, 2] - boxes[0, 0]), 2 * K[0, 0] * enc.crop_margin * 3.04 / SCENE_DISTANCE, rel_tol=1e-5
    )


@pytest.mark.parametrize("crop", [None, 32])
def test_outputs_shapes_and_gradients(crop: int | None) -> None:
    torch.manual_seed(0)
    enc = PoseEncoder(image_size=64, crop_size=crop, out_dim=16)
    x = torch.rand(3, 3, 64, 64, requires_grad=True)
    pose = torch.eye(4).repeat(3, 1, 1)
    out = enc(x, pose=pose)
    assert isinstance(out, Encoding)
    assert (
        out.feature.shape == (3, 16) and out.rotation.shape == (3, 3, 3) and out.translation.shape == (3, 3)
    )
    assert (out.located is None) == (crop is None)
    assert_close(torch.linalg.det(out.rotation), torch.ones(3), atol=1e-5, rtol=0)
    loss = out.feature.square().sum() + out.rotation.sum() + out.translation.sum()
    if out.located is not None:
        loss = loss + out.located.sum()
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(torch.isfinite(p.grad).all() for p in enc.parameters() if p.grad is not None)


def test_untrained_head_starts_at_the_identity_and_rotation_only_has_no_translation() -> None:
    enc = PoseEncoder(image_size=32, out_dim=8, translation=False).eval()
    with torch.no_grad():
        out = enc(torch.rand(2, 3, 32, 32))
    assert out.translation is None and out.located is None
    assert float((out.rotation - torch.eye(3)).abs().max()) < 0.5


def test_eval_crops_follow_the_locator_and_training_crops_the_truth() -> None:
    torch.manual_seed(1)
    enc = PoseEncoder(image_size=64, crop_size=32, out_dim=8, crop_jitter=0.0)
    img = torch.rand(2, 3, 64, 64)
    pose = torch.eye(4).repeat(2, 1, 1)
    pose[:, :3, 3] = torch.tensor([[0.5, -0.5, 0.2], [-0.3, 0.1, -0.4]])
    enc.train()
    t_train = enc(img, pose=pose).translation - enc.pose_head(enc(img, pose=pose).feature)[:, 6:9]
    assert_close(t_train, pose[:, :3, 3], atol=1e-5, rtol=0)
    enc.eval()
    with torch.no_grad():
        out = enc(img, pose=pose)  # at test the truth is not used
        t_eval = out.translation - enc.pose_head(out.feature)[:, 6:9]
    assert_close(t_eval, out.located, atol=1e-5, rtol=0)


def test_bad_configuration_is_one_line() -> None:
    with pytest.raises(ValueError, match="crop_size needs poses with a translation"):
        PoseEncoder(image_size=64, crop_size=32, translation=False)
    with pytest.raises(ValueError, match="crop_jitter"):
        PoseEncoder(image_size=64, crop_size=32, crop_jitter=(0.1, 0.1))
    with pytest.raises(ValueError, match="built for 64"):
        PoseEncoder(image_size=64, out_dim=8)(torch.rand(1, 3, 32, 32))


def test_torchvision_trunk_names_match_every_arch() -> None:
    import torchvision

    from posediff.nn.pose_encoder import _TORCHVISION_TRUNK

    for arch in ("resnet18", "resnet34", "resnet50"):
        names = tuple(n for n, _ in getattr(torchvision.models, arch)().named_children())
        assert names[:-2] == _TORCHVISION_TRUNK


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_crop_box_is_an_error_before_roi_align(bad: float) -> None:
    """torchvision's roi_align crashed the process (SIGSEGV, nothing printed) on NaN boxes; the crop
    refuses them first, also when they come from a NaN locator inside ``forward``."""
    from posediff.nn.pose_encoder import CropBoxError

    enc = PoseEncoder(image_size=32, crop_size=16, out_dim=8).eval()
    image = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([[0.0, 0.0, 0.0], [bad, 0.0, 0.0]])
    with pytest.raises(CropBoxError, match="not finite"):
        enc.crop(image, t)
    with torch.no_grad():
        for p in enc.locator.parameters():
            p.fill_(bad)
    with pytest.raises(CropBoxError, match="not finite"):
        enc(image)
    enc.crop(image, torch.zeros(2, 3))  # finite boxes still crop


def _disk_images(radii: list[float], size: int = 128, grey: float = 0.6) -> torch.Tensor:
    """Grey disks of the given radii (pixels) at the image centre on black, edge pixels anti-aliased."""
    yy, xx = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    r = ((xx - size / 2) ** 2 + (yy - size / 2) ** 2).sqrt()
    return torch.stack([(grey * (rad + 0.5 - r).clamp(0, 1)).expand(3, size, size) for rad in radii])


def _size_encoder(cue: str = "size") -> PoseEncoder:
    torch.manual_seed(0)
    enc = PoseEncoder(image_size=128, crop_size=64, out_dim=16, crop_jitter=0.0, depth_cue=cue)
    with torch.no_grad():  # no learned offsets: the depth is the apparent size's alone
        enc.pose_head.weight.zero_()
        enc.locator.depth.weight.zero_()
    return enc


def test_size_depth_follows_the_apparent_size() -> None:
    """``depth_cue="size"``: an object half as large in the image is twice as far (area ∝ 1/z²), for the
    locator and the anchor alike; the reference is the running mean of the training images' log-area."""
    enc = _size_encoder().train()
    radii = [12.0, 16.0, 24.0]
    images = _disk_images(radii)
    pose = torch.eye(4).repeat(3, 1, 1)
    out = enc(images, pose=pose)
    assert out.log_size is not None and bool(torch.isfinite(enc.log_area_mean))
    z_cam = out.translation[:, 2] + SCENE_DISTANCE
    z_loc = out.located[:, 2] + SCENE_DISTANCE
    for z in (z_cam, z_loc):
        # radius ratio 2 → depth ratio 1/2 (edge anti-aliasing: within 2 %)
        assert_close(z[0] / z[2], torch.tensor(radii[2] / radii[0]), rtol=0.02, atol=0.0)
        assert_close(z[1] / z[2], torch.tensor(radii[2] / radii[1]), rtol=0.02, atol=0.0)
    # the first batch sets the reference: the geometric-mean area sits at the scene centre's depth
    assert_close(out.log_size.mean(), torch.tensor(0.0), atol=1e-5, rtol=0.0)


def test_size_reference_is_a_running_mean_kept_in_the_state_dict() -> None:
    enc = _size_encoder().train()
    pose = torch.eye(4).repeat(2, 1, 1)
    enc(_disk_images([10.0, 10.0]), pose=pose)
    first = enc.log_area_mean.clone()
    enc(_disk_images([20.0, 20.0]), pose=pose)
    area_ratio_log = math.log(4.0)
    assert_close(enc.log_area_mean, first + 0.01 * area_ratio_log, rtol=0.0, atol=2e-3)
    enc.eval()
    before = enc.log_area_mean.clone()
    enc(_disk_images([30.0]))
    assert torch.equal(enc.log_area_mean, before), "evaluation does not move the reference"
    assert "log_area_mean" in enc.state_dict()
    plain = PoseEncoder(image_size=128, crop_size=64, out_dim=16)
    assert "log_area_mean" not in plain.state_dict() and plain(_disk_images([10.0])).log_size is None


def test_size_depth_moves_the_crop_along_its_ray_and_has_gradients() -> None:
    """The anchor's x, y are the crop centre's ray at the new depth: the projection is unchanged."""
    enc = _size_encoder().train()
    images = _disk_images([12.0, 24.0])
    pose = torch.eye(4).repeat(2, 1, 1)
    pose[:, 0, 3] = 0.8
    out = enc(images, pose=pose)
    t_crop, t = out.crop_translation, out.translation
    u_crop = t_crop[:, 0] / (t_crop[:, 2] + SCENE_DISTANCE)
    u = t[:, 0] / (t[:, 2] + SCENE_DISTANCE)
    assert_close(u, u_crop, rtol=1e-5, atol=1e-6)
    loss = t.square().sum() + out.located.square().sum()
    loss.backward()
    grads = [p.grad for p in enc.parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
    assert float(enc.pose_head.weight.grad.abs().sum()) > 0


def test_size_depth_bad_configuration_is_one_line() -> None:
    with pytest.raises(ValueError, match="unknown depth_cue 'area'; choose one of: null, size, size_head"):
        PoseEncoder(image_size=64, crop_size=32, depth_cue="area")
    with pytest.raises(ValueError, match="depth_cue=size needs locate-then-crop"):
        PoseEncoder(image_size=64, depth_cue="size")
    with pytest.raises(ValueError, match=r"background_level must be in \(0, 1\)"):
        PoseEncoder(image_size=64, crop_size=32, depth_cue="size", background_level=1.5)


def test_size_head_leaves_the_locator_depth_regressed() -> None:
    """``depth_cue="size_head"``: the anchor's depth follows the apparent size, the locator's does not
    (its untrained linear depth head says the scene centre for every size)."""
    enc = _size_encoder("size_head").train()
    out = enc(_disk_images([12.0, 24.0]), pose=torch.eye(4).repeat(2, 1, 1))
    assert_close(out.located[:, 2], torch.zeros(2))
    z = out.translation[:, 2] + SCENE_DISTANCE
    assert_close(z[0] / z[1], torch.tensor(2.0), rtol=0.02, atol=0.0)


def _shaded_polygon(size: int = 128, supersample: int = 8) -> tuple[torch.Tensor, float]:
    """A hexagon made of two faces of different shade (0.3 and 0.8) on black, each pixel the mean of
    supersample² sub-pixels (anti-aliased edges), and its exact area in pixels."""
    n = size * supersample
    yy, xx = torch.meshgrid(torch.arange(n) + 0.5, torch.arange(n) + 0.5, indexing="ij")
    x, y = xx / supersample - size / 2, yy / supersample - size / 2
    R = 20.3
    ang = torch.arange(6) * math.pi / 3 + 0.2
    vx, vy = R * torch.cos(ang), R * torch.sin(ang)
    inside = torch.ones_like(x, dtype=torch.bool)
    for k in range(6):  # convex: on the left of every edge
        ex, ey = vx[(k + 1) % 6] - vx[k], vy[(k + 1) % 6] - vy[k]
        inside &= ex * (y - vy[k]) - ey * (x - vx[k]) >= 0
    shade = torch.where(y > 0.3 * x, 0.8, 0.3)
    fine = torch.where(inside, shade, 0.0)
    grey = fine.reshape(size, supersample, size, supersample).mean((1, 3))
    area = 1.5 * math.sqrt(3) * R**2
    return grey, area


def test_coverage_area_counts_edge_pixels_by_their_covered_fraction() -> None:
    """Against an exactly known area with anti-aliased edges and two shades: the coverage estimate is
    within 0.5 % (edge pixels by grey / inner shade); the threshold estimate counts partly covered
    pixels whole and is percents too large."""
    from posediff.nn.pose_encoder import coverage_area

    grey, area = _shaded_polygon()
    got = float(coverage_area(grey[None])) * grey.numel()
    assert abs(got / area - 1.0) < 0.005
    threshold = float((grey / 0.05).clamp(0, 1).sum())
    assert threshold / area - 1.0 > 0.02
    enc = PoseEncoder(
        image_size=128, crop_size=64, out_dim=16, depth_cue="size_head", area_estimate="coverage"
    )
    assert enc.area_estimate == "coverage"
    with pytest.raises(ValueError, match="unknown area_estimate 'exact'; choose one of: threshold, coverage"):
        PoseEncoder(image_size=128, crop_size=64, depth_cue="size_head", area_estimate="exact")


def test_depth_head_from_the_embedding_starts_as_the_linear_head_and_learns() -> None:
    """``depth_head="embedding"``: an MLP of the (detached) invariant embeddings adds to the depth
    offset; zero-initialised, the anchor is the linear head's; it gets gradients, the embedding none
    through it."""
    torch.manual_seed(0)
    enc = PoseEncoder(image_size=128, crop_size=64, out_dim=16, crop_jitter=0.0, depth_cue="size_head",
                      rotation_head="invariant", depth_head="embedding").train()  # fmt: skip
    images = _disk_images([12.0, 20.0])
    pose = torch.eye(4).repeat(2, 1, 1)
    out = enc(images, pose=pose)
    mlp, enc.depth_mlp = enc.depth_mlp, None
    plain = enc(images, pose=pose)
    enc.depth_mlp = mlp
    assert_close(out.translation, plain.translation)
    out.translation[:, 2].sum().backward()
    assert float(mlp[-1].weight.grad.abs().sum()) > 0
    with pytest.raises(
        ValueError, match="depth_head=embedding needs rotation_head=invariant and a depth_cue"
    ):
        PoseEncoder(image_size=128, crop_size=64, depth_cue="size_head", depth_head="embedding")
    with pytest.raises(ValueError, match="unknown depth_head 'mlp'; choose one of: linear, embedding"):
        PoseEncoder(image_size=128, crop_size=64, depth_cue="size_head", depth_head="mlp")
