"""ResNetEncoder: shapes, normalisation, local weights only, one-line errors, gradients."""

from pathlib import Path

import pytest
import torch

from posediff.nn import ResNetEncoder


@pytest.mark.parametrize(("arch", "size"), [("resnet18", 64), ("resnet18", 70), ("resnet50", 32)])
def test_shapes_and_gradients(arch: str, size: int) -> None:
    enc = ResNetEncoder(arch, out_dim=24, image_size=size)
    x = torch.rand(2, 3, size, size, requires_grad=True)
    y = enc(x)
    assert y.shape == (2, 24) and torch.isfinite(y).all()
    y.square().sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_features_depend_on_where_the_object_is() -> None:
    """Flatten (not pooling) keeps the layout: the same blob in two places gives two features."""
    torch.manual_seed(0)
    enc = ResNetEncoder("resnet18", out_dim=16, image_size=64).eval()
    a, b = torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 64, 64)
    a[..., 4:20, 4:20] = 1.0
    b[..., 44:60, 44:60] = 1.0
    with torch.no_grad():
        fa, fb = enc(a), enc(b)
    assert (fa - fb).abs().max() > 1e-3 * fa.abs().max()


def test_local_weights_load_and_missing_file_is_one_line(tmp_path: Path) -> None:
    import torchvision

    torch.manual_seed(1)
    net = torchvision.models.resnet18(weights=None)
    path = tmp_path / "r18.pth"
    torch.save(net.state_dict(), path)
    enc = ResNetEncoder("resnet18", image_size=32, weights=path)
    torch.testing.assert_close(enc.trunk[0].weight, net.conv1.weight)
    with pytest.raises(FileNotFoundError, match="never downloads"):
        ResNetEncoder("resnet18", weights=tmp_path / "nope.pth")
    with pytest.raises(ValueError, match="available: resnet18, resnet34, resnet50"):
        ResNetEncoder("vit")
    with pytest.raises(ValueError, match="built for 32×32"):
        enc(torch.rand(1, 3, 64, 64))
