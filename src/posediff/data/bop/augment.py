"""Hard image augmentation of training crops with kornia (runs on the batch, on the GPU when there is one).

The authors apply an imgaug list (GDR-Net's; ``../shared/docs/reference-implementation.md`` §9.4) to
80 % of the training images; :class:`HardAugment` applies kornia's counterparts, each with its own
probability, to a fraction ``p`` of the crops: dropout of patches, Gaussian blur, sharpness,
contrast, brightness, saturation, inversion, per-image multiplicative colour, Gaussian noise and
grey-scale. Crops are masked to the object's visible pixels afterwards again (the data module does
this), so the background stays black.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class HardAugment(nn.Module):
    """``HardAugment(p=0.8)(images (B, 3, H, W) in [0, 1]) → augmented images in [0, 1]``."""

    def __init__(self, p: float = 0.8) -> None:
        super().__init__()
        import kornia.augmentation as KA

        if not 0.0 <= p <= 1.0:
            raise ValueError(f"augmentation probability must be in [0, 1], got {p}")
        self.p = float(p)
        self.ops = KA.ImageSequential(
            KA.RandomErasing(scale=(0.01, 0.05), ratio=(0.5, 2.0), p=0.5),
            KA.RandomGaussianBlur(kernel_size=(7, 7), sigma=(0.1, 3.0), p=0.4),
            KA.RandomSharpness(sharpness=(0.0, 1.0), p=0.3),
            KA.RandomContrast(contrast=(0.3, 2.2), p=0.5),
            KA.RandomBrightness(brightness=(0.6, 1.4), p=0.5),
            KA.RandomSaturation(saturation=(0.0, 3.0), p=0.3),
            KA.RandomInvert(p=0.06),
            KA.ColorJiggle(brightness=0.4, p=0.5),
            KA.RandomGaussianNoise(std=0.04, p=0.1),
            KA.RandomGrayscale(p=0.25),
            random_apply=False,
        )

    def forward(self, images: Tensor) -> Tensor:
        if self.p == 0.0 or images.shape[0] == 0:
            return images
        out = self.ops(images).clamp(0.0, 1.0)
        keep = torch.rand(images.shape[0], device=images.device) >= self.p
        return torch.where(keep[:, None, None, None], images, out)


__all__ = ["HardAugment"]
