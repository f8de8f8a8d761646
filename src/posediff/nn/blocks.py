"""Conditioned MLP blocks: the Fourier block (paper Eq. 13) and the scale-bias (FiLM) block.

Every block maps a hidden state ``h`` of shape ``(..., dim)`` and a condition ``c`` of shape
``(..., cond_dim)`` to ``(..., dim)``. The condition enters only through its projection

    [a, b] = Linear(cond_dim → 2·dim)(SiLU(c)),   a, b: (..., dim),

which :meth:`ConditionedBlock.condition` computes on its own, so that a caller can project each
condition *once* (e.g. once per image, shape ``(B, 1, 2·dim)``) and let it broadcast over many
samples ``h`` of shape ``(B, N, dim)`` through ``forward(h, projected=...)``. The leading dims of
the condition (or its projection) must broadcast against those of ``h``.

Blocks are registered by name (``ConditionedBlock.lookup("fourier")``); a new variant is added by
subclassing with ``name=...`` and implementing :meth:`ConditionedBlock.modulate`.

Weights use the reference's (flax) defaults: LeCun-normal kernels (truncated normal, variance
1/fan_in) and zero biases (reference-implementation.md §5.2); see :class:`LecunLinear`.
"""

import math
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .._registry import Registered

__all__ = [
    "ACTIVATIONS",
    "ConditionedBlock",
    "FourierBlock",
    "LecunLinear",
    "ScaleBiasBlock",
    "make_activation",
]

# std of a standard normal truncated to [-2, 2]; dividing by it restores unit variance (as flax does)
_TRUNCATED_NORMAL_STD = 0.87962566103423978


class Sin(nn.Module):
    """``sin`` as a module (the reference block's own default activation)."""

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(x)


#: activation name → factory; "leaky_relu" (slope 0.01) is what the reference head uses
ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "leaky_relu": lambda: nn.LeakyReLU(0.01),
    "silu": nn.SiLU,
    "relu": nn.ReLU,
    "gelu": nn.GELU,
    "sin": Sin,
}


def make_activation(name: str) -> nn.Module:
    """A fresh activation module by name; unknown names raise a ``ValueError`` listing the known ones."""
    try:
        factory = ACTIVATIONS[name]
    except KeyError:
        known = ", ".join(sorted(ACTIVATIONS))
        raise ValueError(f"unknown activation {name!r}; known: {known}") from None
    return factory()


class LecunLinear(nn.Linear):
    """``nn.Linear`` initialised like flax's ``Dense``: LeCun-normal kernel, zero bias.

    The kernel is drawn from a normal with std ``sqrt(1/fan_in)``, truncated at two standard
    deviations (and rescaled so that the truncated distribution keeps that std).
    """

    def reset_parameters(self) -> None:
        fan_in = self.in_features
        if fan_in > 0:
            std = math.sqrt(1.0 / fan_in) / _TRUNCATED_NORMAL_STD
            nn.init.trunc_normal_(self.weight, mean=0.0, std=std, a=-2.0 * std, b=2.0 * std)
        if self.bias is not None:
            nn.init.zeros_(self.bias)


class ConditionedBlock(nn.Module, Registered, family=True):
    """Base of the conditioned blocks: ``(h (..., dim), c (..., cond_dim)) -> (..., dim)``.

    Args:
        dim: width of the hidden state ``h`` (input and output).
        cond_dim: width of the condition ``c``.
        activation: name of the activation applied to ``h`` inside the block (see ``ACTIVATIONS``).

    Subclasses implement :meth:`modulate`, which receives ``a, b`` (each ``(..., dim)``, the two
    halves of :meth:`condition`).
    """

    family_label: ClassVar[str] = "conditioned block"

    def __init__(self, dim: int, cond_dim: int, activation: str = "leaky_relu") -> None:
        super().__init__()
        if dim < 1 or cond_dim < 1:
            raise ValueError(f"dim and cond_dim must be >= 1, got dim={dim}, cond_dim={cond_dim}")
        self.dim = int(dim)
        self.cond_dim = int(cond_dim)
        self.activation_name = activation
        self.act = make_activation(activation)
        self.cond_proj = LecunLinear(cond_dim, 2 * dim)

    def condition(self, c: Tensor) -> Tensor:
        """Project a condition ``(..., cond_dim)`` to ``[a, b] = Linear(SiLU(c))``: ``(..., 2·dim)``.

        Compute this once per distinct condition and pass it as ``forward(h, projected=...)``.
        """
        if c.shape[-1] != self.cond_dim:
            raise ValueError(f"condition has {c.shape[-1]} features, expected cond_dim={self.cond_dim}")
        return self.cond_proj(F.silu(c))

    def forward(self, h: Tensor, c: Tensor | None = None, *, projected: Tensor | None = None) -> Tensor:
        """Apply the block to ``h`` ``(..., dim)`` given either ``c`` or its ``projected`` form.

        Exactly one of ``c`` (``(..., cond_dim)``) and ``projected`` (``(..., 2·dim)``, from
        :meth:`condition`) must be given; its leading dims must broadcast against ``h``'s.
        Returns ``(..., dim)`` (the broadcast leading shape).
        """
        if (c is None) == (projected is None):
            raise ValueError("pass exactly one of the condition c and its projection `projected`")
        if h.shape[-1] != self.dim:
            raise ValueError(f"hidden state has {h.shape[-1]} features, expected dim={self.dim}")
        if projected is None:
            projected = self.condition(c)  # type: ignore[arg-type]
        elif projected.shape[-1] != 2 * self.dim:
            raise ValueError(
                f"projected condition has {projected.shape[-1]} features, expected 2·dim={2 * self.dim}"
            )
        a, b = projected.chunk(2, dim=-1)
        return self.modulate(h, a, b)

    def modulate(self, h: Tensor, a: Tensor, b: Tensor) -> Tensor:
        """The block proper, given the condition's two halves ``a, b`` (broadcastable to ``h``)."""
        raise NotImplementedError(f"{type(self).__name__} must implement modulate()")

    def extra_repr(self) -> str:
        return f"dim={self.dim}, cond_dim={self.cond_dim}, activation={self.activation_name!r}"


class FourierBlock(ConditionedBlock, name="fourier"):
    """Fourier-conditioned block, paper Eq. 13 (Sec. 3.4, "The Proposed Framework")::

        f_i(x, c) = Σ_j W_ij (A_j(c) cos(π x_j) + B_j(c) sin(π x_j))

    as in the reference head (``FourierMlpBlock``)::

        u   = Linear(dim → dim)(act(h))            # x in Eq. 13
        u   = a ⊙ cos(π u) + b ⊙ sin(π u)          # A(c), B(c) = a, b
        out = Linear(dim → dim)(u) + Linear(dim → dim)(h)   # W of Eq. 13, plus a learned skip
    """

    def __init__(self, dim: int, cond_dim: int, activation: str = "leaky_relu") -> None:
        super().__init__(dim, cond_dim, activation)
        self.inner = LecunLinear(dim, dim)
        self.outer = LecunLinear(dim, dim)
        self.skip = LecunLinear(dim, dim)

    def modulate(self, h: Tensor, a: Tensor, b: Tensor) -> Tensor:
        u = math.pi * self.inner(self.act(h))
        u = a * torch.cos(u) + b * torch.sin(u)
        return self.outer(u) + self.skip(h)


class ScaleBiasBlock(ConditionedBlock, name="scale_bias"):
    """Scale-bias (FiLM) block, the paper's baseline conditioning ``f(x, c) = A(c) x + B(c)``
    (Sec. 3.4, inline, after DDPM/NCSN); the reference's ``MlpBlock``::

        u   = Linear(dim → dim)(act(h)) ⊙ (1 + a) + b
        out = Linear(dim → dim)(act(u)) + Linear(dim → dim)(h)   # learned skip
    """

    def __init__(self, dim: int, cond_dim: int, activation: str = "leaky_relu") -> None:
        super().__init__(dim, cond_dim, activation)
        self.inner = LecunLinear(dim, dim)
        self.outer = LecunLinear(dim, dim)
        self.skip = LecunLinear(dim, dim)

    def modulate(self, h: Tensor, a: Tensor, b: Tensor) -> Tensor:
        u = self.inner(self.act(h)) * (1.0 + a) + b
        return self.outer(self.act(u)) + self.skip(h)
