"""Noise schedules: the increasing noise levels ``σ_0 < σ_1 < … < σ_{L−1}`` of the forward process.

Training draws a level ``i ~ U{0, …, L−1}`` per noisy sample (paper Alg. 1); sampling walks down a
subset of the levels, ``timesteps(num_steps)``, so a model trained on ``L = 100`` levels can be
sampled with 5, 10 or 50 steps without retraining.

* ``linear`` — the paper's schedule (supplement, "Hyperparameters"): σ linear from 1e-4 to 1.0
  over 100 levels.
* ``power`` — the authors' code (VE power): ``σ_i² = (c₀ + (1 − c₀)·i/L)^p``, ``c₀ = a₀^{1/p}``,
  ``a₀ = 1e-8``, ``p = 3``, ``i = 0 … L−1`` — σ from 1e-4 to 0.985 (the code never trains on
  ``i = L``, σ = 1).
* ``loglinear`` — σ geometric from σ_min to σ_max.

A schedule also maps σ back to a *continuous level index* (``level``), the noise input the
authors feed to the network (the integer index, embedded sinusoidally).
"""

import math
from typing import Any, ClassVar

import torch
from torch import Tensor

from .._registry import Registered


class NoiseSchedule(Registered, family=True):
    """``L`` increasing noise levels; ``sigmas`` is a float64 tensor ``(L,)``."""

    family_label: ClassVar[str] = "noise schedule"
    name: ClassVar[str]

    def __init__(self, num_levels: int = 100) -> None:
        if int(num_levels) < 2:
            raise ValueError(f"{type(self).__name__}: num_levels must be ≥ 2, got {num_levels}")
        self.num_levels = int(num_levels)
        sig = self._sigmas(self.num_levels).to(torch.float64)
        if not bool((sig[1:] > sig[:-1]).all()) or not bool((sig > 0).all()):
            raise ValueError(f"{type(self).__name__}: noise levels must be positive and increasing")
        self._table = sig

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_levels={self.num_levels}, σ ∈ [{self.sigma_min:.3g}, {self.sigma_max:.3g}])"

    # ------------------------------------------------------------------ levels
    @property
    def sigmas(self) -> Tensor:
        """The noise levels, ``(L,)`` float64, increasing."""
        return self._table.clone()

    @property
    def sigma_min(self) -> float:
        return float(self._table[0])

    @property
    def sigma_max(self) -> float:
        return float(self._table[-1])

    def sigma(self, levels: Tensor, *, dtype: torch.dtype | None = None) -> Tensor:
        """σ at integer level indices (any shape)."""
        table = self._table.to(device=levels.device, dtype=dtype or torch.get_default_dtype())
        return table[levels.long()]

    def level(self, sigma: Tensor) -> Tensor:
        """The continuous level index of σ: piecewise-linear in ``log σ`` between the table entries.

        Exact at the table's σ (``level(sigma(i)) == i``); clamped to ``[0, L−1]`` outside it.
        """
        log_table = self._table.log().to(device=sigma.device, dtype=torch.float64)
        ls = sigma.to(torch.float64).clamp_min(1e-300).log()
        if torch.compiler.is_compiling() or torch.jit.is_tracing():
            # being exported (torch.export / ONNX / TorchScript): searchsorted (left) as a count of the
            # entries below — the same index, in ops every exporter has
            idx = (log_table < ls.unsqueeze(-1)).sum(-1)
        else:
            idx = torch.searchsorted(log_table, ls.reshape(-1).contiguous()).reshape(ls.shape)
        idx = idx.clamp(1, self.num_levels - 1)
        lo, hi = log_table[idx - 1], log_table[idx]
        frac = ((ls - lo) / (hi - lo)).clamp(0.0, 1.0)
        return (idx - 1 + frac).to(sigma.dtype)

    def sample_levels(
        self, batch_shape: tuple[int, ...], *, generator: torch.Generator | None = None, device: Any = None
    ) -> Tensor:
        """Training levels ``i ~ U{0, …, L−1}`` (paper Alg. 1), a long tensor of ``batch_shape``."""
        return torch.randint(0, self.num_levels, tuple(batch_shape), generator=generator, device=device)

    def timesteps(self, num_steps: int | None = None) -> Tensor:
        """The level indices a sampler visits, descending from ``L−1`` to ``0``: ``(num_steps,)`` long.

        ``num_steps=None`` means every level. Fewer steps pick evenly spaced levels (rounded), always
        including the top and the bottom level, so a model trained on ``L`` levels is sampled with
        fewer steps on levels it was trained at.
        """
        n = self.num_levels if num_steps is None else int(num_steps)
        if not 1 <= n <= self.num_levels:
            raise ValueError(
                f"num_steps must be in [1, {self.num_levels}] for this schedule, got {num_steps}"
            )
        if n == 1:
            return torch.tensor([self.num_levels - 1])
        steps = torch.linspace(self.num_levels - 1, 0, n, dtype=torch.float64).round().long()
        return steps

    # ------------------------------------------------------------------ to implement
    def _sigmas(self, num_levels: int) -> Tensor:
        raise NotImplementedError


class LinearSchedule(NoiseSchedule, name="linear"):
    """σ linear from ``sigma_min`` to ``sigma_max`` over ``num_levels`` levels (the paper's schedule)."""

    def __init__(self, num_levels: int = 100, sigma_min: float = 1e-4, sigma_max: float = 1.0) -> None:
        self._range = (float(sigma_min), float(sigma_max))
        super().__init__(num_levels)

    def _sigmas(self, num_levels: int) -> Tensor:
        lo, hi = self._range
        return torch.linspace(lo, hi, num_levels, dtype=torch.float64)


class LogLinearSchedule(NoiseSchedule, name="loglinear"):
    """σ geometric (linear in ``log σ``) from ``sigma_min`` to ``sigma_max``."""

    def __init__(self, num_levels: int = 100, sigma_min: float = 1e-4, sigma_max: float = 1.0) -> None:
        self._range = (float(sigma_min), float(sigma_max))
        super().__init__(num_levels)

    def _sigmas(self, num_levels: int) -> Tensor:
        lo, hi = self._range
        return torch.logspace(math.log10(lo), math.log10(hi), num_levels, dtype=torch.float64)


class PowerSchedule(NoiseSchedule, name="power"):
    """The authors' VE power schedule: ``σ_i² = (a₀^{1/p} + (a₁^{1/p} − a₀^{1/p})·i/L)^p``, ``i < L``.

    Defaults ``a₀ = 1e-8``, ``a₁ = 1``, ``p = 3``, ``L = 100`` give σ_0 = 1e-4, σ_50 = 0.3547,
    σ_99 = 0.98507 (the code's values; its σ_100 = 1 is never trained or sampled).
    """

    def __init__(
        self, num_levels: int = 100, noise_start: float = 1e-8, noise_end: float = 1.0, power: float = 3.0
    ) -> None:
        self._params = (float(noise_start), float(noise_end), float(power))
        super().__init__(num_levels)

    def _sigmas(self, num_levels: int) -> Tensor:
        a0, a1, p = self._params
        c0, c1 = a0 ** (1 / p), a1 ** (1 / p)
        i = torch.arange(num_levels, dtype=torch.float64)
        return ((c0 + (c1 - c0) * i / num_levels) ** p).sqrt()
