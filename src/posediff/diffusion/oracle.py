"""The exact denoiser of a known target: a weighted mixture of point masses on the group.

For data ``p = Σ_k w_k δ(C_k)`` the noisy marginal is ``p_σ(X̃) = Σ_k w_k p_σ(X̃ | C_k)``. The
network that minimises the DSM loss outputs the posterior mean of its target,
``Σ_k π_k(X̃) T(z_k)`` with ``z_k = Log(C_k⁻¹ X̃)`` and responsibilities
``π_k ∝ w_k p_σ(X̃ | C_k)`` (the kernel density, paper Eq. 3). With the ``closed_form`` target this is
exactly the score of ``p_σ`` (``∇ log Σ_k w_k p_k = Σ_k π_k ∇ log p_k``); with the surrogate it is
what a perfectly trained surrogate network converges to. Samplers can therefore be tested, and
timed, with no training (``tests/diffusion/test_samplers_oracle.py``, ``benchmarks/sampler.py``).
"""

from typing import Any

import torch
from torch import Tensor

from .process import Diffusion


def mixture_log_weights(centers: Tensor, weights: Tensor | None) -> Tensor:
    """``log`` of a point-mass mixture's weights, ``centers.shape[:-2]``; ``None``: uniform over its ``K``."""
    if weights is None:
        k = centers.shape[-3]
        weights = torch.full(centers.shape[:-2], 1.0 / k, dtype=centers.dtype, device=centers.device)
    return torch.log(weights)


class MixtureOracle:
    """``denoise_fn`` for a mixture of point masses (``centers (K, n, n)`` or per input ``(B, K, n, n)``).

    Args:
        diffusion: supplies the kernel, the score target and the output parameterisation.
        centers: the point masses.
        weights: ``(K,)`` or ``(B, K)`` mixture weights (default uniform).
    """

    def __init__(self, diffusion: Diffusion, centers: Tensor, weights: Tensor | None = None) -> None:
        self.diffusion = diffusion
        self.centers = centers
        self.log_weights = mixture_log_weights(centers, weights)

    def __call__(self, x: Tensor, sigma: Tensor, cond: Any = None) -> Tensor:
        d = self.diffusion
        g = d.group
        c = self.centers.to(x.dtype)
        if c.ndim == 3:  # (K, n, n): same mixture for every input
            c = c.expand(x.shape[0], *c.shape)
        # z_k = Log(C_k^-1 X̃): (B, N, K, dim)
        ck = c.unsqueeze(1)  # (B, 1, K, n, n)
        z = g.rminus(ck, x.unsqueeze(2))
        sig = sigma.unsqueeze(-1).expand(z.shape[:-1])
        logw = self.log_weights.to(x.dtype)
        logw = logw.expand(x.shape[0], -1) if logw.ndim == 1 else logw
        log_r = d.kernel.log_prob_tangent(z, sig) + logw.unsqueeze(1)
        resp = torch.softmax(log_r, dim=-1)  # (B, N, K)
        target = d.from_score(d.score_target(d.kernel, z, sig), sig)
        return (resp.unsqueeze(-1) * target).sum(-2)
