"""``ResNetEncoder``: the image encoder, run once per image (paper §4.4 and supplement).

A torchvision ResNet18 / 34 / 50 trunk (``weights=None`` by default, or a **local** weights file —
never a download), ImageNet normalisation of ``[0, 1]`` RGB input, and the paper's feature head: a
1×1 convolution that narrows the last feature map, flatten (which keeps the spatial layout, so the
translation stays visible), and a dense layer to the condition size.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor, nn

ARCHS: tuple[str, ...] = ("resnet18", "resnet34", "resnet50")
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


class ResNetEncoder(nn.Module):
    """``(B, 3, H, W)`` images in [0, 1] → ``(B, out_dim)`` features.

    Args:
        arch: ``resnet18`` | ``resnet34`` | ``resnet50``.
        out_dim: condition size (the denoiser's ``cond_dim``).
        image_size: input side in pixels (sets the flattened size of the head).
        head_channels: channels of the 1×1 convolution.
        weights: ``None`` (random init) or the path of a local torchvision state dict (``.pth``),
            loaded with ``weights_only=True``; a missing file is a one-line error.
    """

    def __init__(
        self,
        arch: str = "resnet18",
        out_dim: int = 256,
        *,
        image_size: int = 224,
        head_channels: int = 32,
        weights: str | os.PathLike[str] | None = None,
    ) -> None:
        super().__init__()
        import torchvision

        if arch not in ARCHS:
            raise ValueError(f"unknown encoder arch {arch!r}; available: {', '.join(ARCHS)}")
        net = getattr(torchvision.models, arch)(weights=None)
        if weights is not None:
            path = Path(weights)
            if not path.is_file():
                raise FileNotFoundError(
                    f"encoder weights file {path} not found (posediff never downloads; give a local "
                    f"torchvision {arch} state dict, or weights=null)"
                )
            net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.arch, self.out_dim, self.image_size = arch, int(out_dim), int(image_size)
        self.trunk = nn.Sequential(*list(net.children())[:-2])  # drop avgpool and fc
        channels = net.fc.in_features
        side = -(-int(image_size) // 32)  # ResNet downsamples by 32 (ceil)
        self.head = nn.Sequential(
            nn.Conv2d(channels, head_channels, kernel_size=1),
            nn.ReLU(inplace=True),
            nn.Flatten(),
            nn.Linear(head_channels * side * side, self.out_dim),
        )
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, image: Tensor) -> Tensor:
        if image.shape[-2:] != (self.image_size, self.image_size):
            raise ValueError(
                f"encoder built for {self.image_size}×{self.image_size} images, got {tuple(image.shape[-2:])}"
            )
        return self.head(self.trunk((image - self.mean) / self.std))

    def extra_repr(self) -> str:
        return f"arch={self.arch}, image_size={self.image_size}, out_dim={self.out_dim}"


__all__ = ["ARCHS", "ResNetEncoder"]
