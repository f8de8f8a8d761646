"""The image-free denoising network: an MLP of conditioned blocks on Lie-algebra vectors.

This is the "denoising part" of the paper's framework (Sec. 3.4, Fig. 3 left): it takes a noisy
pose as a tangent vector x̃_i ∈ 𝔤 (``(..., in_dim)``, e.g. 6 for SE(3)/R3SO3, 3 for SO(3)), a
scalar noise-level input and a condition ``c`` (e.g. an image feature computed once per image by
a separate encoder) and returns a tangent vector ``(..., out_dim)``: the score s_θ(x̃_i, σ_i)
(Eq. 6, used in the Langevin update Eq. 7) or, as in the reference, the noise ẑ from which the
surrogate score (Eq. 12) follows.

Architecture (reference head, reference-implementation.md §5.2), with F = ``num_frequencies``::

    t = Linear(2F → time_dim)(emb(noise))                   # time embedding, with bias
    h = Linear(in_dim·2F → hidden_dim, no bias)(emb(x))    # pose embedding
    for each of num_layers:
        h = Block(h, c)                                     # condition block (omitted if cond_dim=0)
        h = Block(h, t)                                     # time block
    out = Linear(hidden_dim → out_dim)(act(h))

``emb`` is :class:`~posediff.nn.SinusoidalEmbedding` (per scalar component) and ``Block`` is the
registered :class:`~posediff.nn.ConditionedBlock` named by ``block`` ("fourier", paper Eq. 13, or
"scale_bias"). The condition is projected *once per condition*: with ``x`` of shape ``(B, N, ·)``
and ``cond`` of shape ``(B, C)`` the condition block's projection runs on ``(B, 1, C)`` and
broadcasts over the N samples; the noisy samples never force a copy of the condition.
"""

import torch
from torch import Tensor, nn

from .blocks import ConditionedBlock, LecunLinear, make_activation
from .embedding import SinusoidalEmbedding

__all__ = ["MLPDenoiser"]


class MLPDenoiser(nn.Module):
    """Conditioned MLP denoiser ``(x (..., in_dim), noise (...), cond) -> (..., out_dim)``.

    Args:
        cond_dim: width of the condition (512 for the reference's image feature); 0 for an
            unconditional network, which then has no condition blocks and takes ``cond=None``.
        in_dim: width of the tangent input ``x``.
        out_dim: width of the output.
        hidden_dim: width of the hidden state (reference: 256).
        num_layers: number of (condition block, time block) pairs (reference: 1).
        block: registry name of the block class: "fourier" (Eq. 13) or "scale_bias" (FiLM).
        num_frequencies: F of the sinusoidal embeddings of ``x`` and ``noise`` (reference: 128).
        time_dim: width of the time embedding that conditions the time blocks (reference: 256).
        activation: activation name, used inside the blocks and before the output layer.
        zero_init_output: start with a zero output layer (the network then outputs 0 at init).
            The reference does not do this.
        pose_min_period, pose_max_period: fastest and slowest period of the embedding of ``x``
            (reference: 1 and 1e4; see :class:`~posediff.nn.SinusoidalEmbedding`). The noise-level
            embedding keeps the reference's frequencies.

    All linear layers are initialised like the reference (flax): LeCun-normal kernels, zero biases.
    """

    def __init__(
        self,
        cond_dim: int,
        in_dim: int,
        out_dim: int,
        *,
        hidden_dim: int = 256,
        num_layers: int = 1,
        block: str = "fourier",
        num_frequencies: int = 128,
        time_dim: int = 256,
        activation: str = "leaky_relu",
        zero_init_output: bool = False,
        pose_min_period: float = 1.0,
        pose_max_period: float = 1e4,
    ) -> None:
        super().__init__()
        if cond_dim < 0 or in_dim < 1 or out_dim < 1 or hidden_dim < 1 or time_dim < 1 or num_layers < 1:
            raise ValueError(
                "need cond_dim >= 0 and in_dim, out_dim, hidden_dim, time_dim, num_layers >= 1; got "
                f"cond_dim={cond_dim}, in_dim={in_dim}, out_dim={out_dim}, hidden_dim={hidden_dim}, "
                f"time_dim={time_dim}, num_layers={num_layers}"
            )
        block_cls = ConditionedBlock.lookup(block)  # unknown name: KeyError listing the registered ones
        self.cond_dim = int(cond_dim)
        self.in_dim = int(in_dim)
        self.out_dim = int(out_dim)
        self.hidden_dim = int(hidden_dim)
        self.num_layers = int(num_layers)
        self.block = block
        self.time_dim = int(time_dim)
        self.zero_init_output = bool(zero_init_output)

        self.embedding = SinusoidalEmbedding(num_frequencies)
        self.pose_embedding = SinusoidalEmbedding(num_frequencies, pose_max_period, pose_min_period)
        self.time_proj = LecunLinear(self.embedding.out_features(1), time_dim)
        self.pose_proj = LecunLinear(self.pose_embedding.out_features(in_dim), hidden_dim, bias=False)
        self.cond_blocks = nn.ModuleList(
            [block_cls(hidden_dim, cond_dim, activation) for _ in range(num_layers)] if cond_dim > 0 else []
        )
        self.time_blocks = nn.ModuleList(
            [block_cls(hidden_dim, time_dim, activation) for _ in range(num_layers)]
        )
        self.out_act = make_activation(activation)
        self.out = LecunLinear(hidden_dim, out_dim)
        if zero_init_output:
            self._zero_output()

    def _zero_output(self) -> None:
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def reset_parameters(self) -> None:
        """Re-draw every parameter (LeCun-normal kernels, zero biases; zero output if so configured)."""
        for module in self.modules():
            if isinstance(module, LecunLinear):
                module.reset_parameters()
        if self.zero_init_output:
            self._zero_output()

    def forward(self, x: Tensor, noise: Tensor | float, cond: Tensor | None = None) -> Tensor:
        """Denoise ``x`` at noise level ``noise`` given ``cond``.

        Args:
            x: tangent vectors ``(*lead, in_dim)``, e.g. ``(B, N, in_dim)`` (N samples per
                condition) or ``(M, in_dim)``.
            noise: the scalar noise-level input, one per sample: shape ``lead`` (or ``(*lead, 1)``);
                any shape with ``len(lead)`` dims that broadcasts to ``lead`` (e.g. ``(B, 1)``, one
                level per condition), or a 0-d tensor / Python number for all samples. What scalar
                it is (a noise-level index 0..99 as in the reference, σ, log σ, …) is up to the
                caller; integer tensors are converted to ``x``'s dtype.
            cond: the condition, ``(*p, cond_dim)`` where ``p`` is a prefix of ``lead`` (e.g.
                ``(B, cond_dim)`` for ``x`` ``(B, N, ·)``, broadcast over N) or ``lead`` itself
                (e.g. ``(B, N, cond_dim)``); size-1 dims broadcast. ``None`` iff ``cond_dim == 0``.

        Returns:
            ``(*lead, out_dim)``.
        """
        if x.ndim < 1 or x.shape[-1] != self.in_dim:
            raise ValueError(f"x must be (..., in_dim={self.in_dim}), got shape {tuple(x.shape)}")
        lead = x.shape[:-1]
        noise = self._noise(noise, lead, x)
        cond = self._cond(cond, lead)

        t = self.time_proj(self.embedding(noise.unsqueeze(-1)))  # (*noise.shape, time_dim)
        h = self.pose_proj(self.pose_embedding(x))  # (*lead, hidden_dim)
        for i, time_block in enumerate(self.time_blocks):
            if cond is not None:
                cond_block = self.cond_blocks[i]
                # projected on cond's own (un-expanded) shape, e.g. (B, 1, 2·hidden), then broadcast
                h = cond_block(h, projected=cond_block.condition(cond))
            h = time_block(h, t)
        return self.out(self.out_act(h))

    def _noise(self, noise: Tensor | float, lead: torch.Size, x: Tensor) -> Tensor:
        noise = torch.as_tensor(noise, device=x.device)
        noise = noise.to(x.dtype if x.is_floating_point() else torch.get_default_dtype())
        if noise.ndim == 0:
            noise = noise.reshape((1,) * len(lead))
        elif noise.ndim == len(lead) + 1 and noise.shape[-1] == 1:
            noise = noise.squeeze(-1)
        if noise.ndim != len(lead) or not _broadcasts_to(noise.shape, lead):
            raise ValueError(
                f"noise must have shape {tuple(lead)} (or broadcast to it with the same number of dims, "
                f"or be a scalar); got {tuple(noise.shape)} for x of shape {(*lead, self.in_dim)}"
            )
        return noise

    def _cond(self, cond: Tensor | None, lead: torch.Size) -> Tensor | None:
        if self.cond_dim == 0:
            if cond is not None:
                raise ValueError("this denoiser has cond_dim=0 and takes no condition (pass cond=None)")
            return None
        if cond is None:
            raise ValueError(f"a condition of width cond_dim={self.cond_dim} is required")
        if cond.ndim < 1 or cond.shape[-1] != self.cond_dim:
            raise ValueError(f"cond must be (..., cond_dim={self.cond_dim}), got shape {tuple(cond.shape)}")
        prefix = cond.shape[:-1]
        if len(prefix) > len(lead):
            raise ValueError(
                f"cond of shape {tuple(cond.shape)} has more leading dims than x ({tuple(lead)})"
            )
        # (B, C) with lead (B, N) -> (B, 1, C): a view, so the projection runs once per condition
        cond = cond.reshape(*prefix, *(1,) * (len(lead) - len(prefix)), self.cond_dim)
        if not _broadcasts_to(cond.shape[:-1], lead):
            raise ValueError(
                f"cond of shape {tuple(cond.shape)} does not broadcast against x's leading shape {tuple(lead)}"
            )
        return cond

    def extra_repr(self) -> str:
        return (
            f"cond_dim={self.cond_dim}, in_dim={self.in_dim}, out_dim={self.out_dim}, "
            f"hidden_dim={self.hidden_dim}, num_layers={self.num_layers}, block={self.block!r}, "
            f"time_dim={self.time_dim}, zero_init_output={self.zero_init_output}, "
            f"pose_periods=({self.pose_embedding.min_period:g}, {self.pose_embedding.max_period:g})"
        )


def _broadcasts_to(shape: torch.Size, target: torch.Size) -> bool:
    """Whether ``shape`` (same number of dims as ``target``) broadcasts to exactly ``target``."""
    return len(shape) == len(target) and all(s in (1, t) for s, t in zip(shape, target, strict=True))
