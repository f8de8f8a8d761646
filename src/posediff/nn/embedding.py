"""Sinusoidal (positional) embedding of scalars, as used for the noise level and the noisy pose.

The paper embeds the noisy tangent vector x̃_i and the time index i "using a positional encoding"
(Sec. 3.4, after Vaswani et al.); the reference head applies it to every scalar component
separately (reference-implementation.md §5.2, ``PosEmbed``)::

    emb(x) = [sin(x f_0), …, sin(x f_{F-1}), cos(x f_0), …, cos(x f_{F-1})],
    f_j = f_0 · (f_{F-1} / f_0)^(j / (F - 1)),  j = 0 … F-1,
    f_0 = 1 / min_period,  f_{F-1} = 1 / max_period    (reference: min_period 1, max_period 1e4).

The reference's fastest frequency is 1 rad⁻¹, which resolves a rotation vector (|x| ≤ π) only
coarsely; ``min_period < 1`` adds faster frequencies (the toy uses 1/16: features that change over
a few degrees), a standard Fourier-feature choice for regressing sharp functions of few inputs.

A ``(..., k)`` input becomes ``(..., k · 2F)``, component-major: entries ``[i·2F, (i+1)·2F)`` hold
the embedding of component ``i`` (first its F sines, then its F cosines).
"""

import math

import torch
from torch import Tensor, nn

__all__ = ["SinusoidalEmbedding"]


class SinusoidalEmbedding(nn.Module):
    """Per-component sinusoidal embedding ``(..., k) -> (..., k · 2F)``; no parameters, no buffers.

    Args:
        num_frequencies: F, the number of frequencies (the reference uses 128, giving 256 features
            per scalar).
        max_period: the slowest frequency is ``1 / max_period`` (reference: 1e4).
        min_period: the fastest frequency is ``1 / min_period`` (reference: 1).

    The frequencies are computed in the input's dtype on the input's device, so the module follows
    the data (no buffers to move). Integer inputs (e.g. a noise-level index) are embedded in the
    default float dtype.
    """

    def __init__(self, num_frequencies: int = 128, max_period: float = 1e4, min_period: float = 1.0) -> None:
        super().__init__()
        if num_frequencies < 1:
            raise ValueError(f"num_frequencies must be >= 1, got {num_frequencies}")
        if not 0 < min_period <= max_period:
            raise ValueError(
                f"need 0 < min_period <= max_period, got min_period={min_period}, max_period={max_period}"
            )
        self.num_frequencies = int(num_frequencies)
        self.max_period = float(max_period)
        self.min_period = float(min_period)

    def out_features(self, k: int) -> int:
        """Width of the embedding of a ``(..., k)`` input: ``k · 2F``."""
        return k * 2 * self.num_frequencies

    def frequencies(self, *, dtype: torch.dtype | None = None, device: torch.device | None = None) -> Tensor:
        """The F frequencies, geometric from ``1/min_period`` to ``1/max_period``, shape ``(F,)``.

        ``[1/min_period]`` when F = 1.
        """
        n = self.num_frequencies
        j = torch.arange(n, dtype=dtype or torch.get_default_dtype(), device=device)
        first = -math.log(self.min_period)
        if n == 1:
            return torch.full_like(j, math.exp(first))
        return torch.exp(first + j * (-math.log(self.max_period / self.min_period) / (n - 1)))

    def forward(self, x: Tensor) -> Tensor:
        """Embed ``x`` of shape ``(..., k)``; returns ``(..., k · 2F)``."""
        if not x.is_floating_point():
            x = x.to(torch.get_default_dtype())
        angles = x.unsqueeze(-1) * self.frequencies(dtype=x.dtype, device=x.device)  # (..., k, F)
        return torch.cat([angles.sin(), angles.cos()], dim=-1).flatten(-2)

    def extra_repr(self) -> str:
        return (
            f"num_frequencies={self.num_frequencies}, max_period={self.max_period:g}, "
            f"min_period={self.min_period:g}"
        )
