"""The sampling loop every evaluation shares: a test loader's batches with ``N`` hypotheses for each
input, the sampler timed alone."""

import time
from collections.abc import Iterator
from typing import Any

import torch
from torch.utils.data import DataLoader

from ..diffusion import Sampler
from ..models import PoseDiffusionModule, PoseModule, PoseRegressionModule


class SampledBatches:
    """The batches of ``loader`` (tensors on the module's device; at most ``max_inputs`` inputs in
    all) with ``num_samples`` hypotheses for each input, ``(batch, x (B, N, n, n))``, timing the
    sampler alone (seeded with ``seed``); :meth:`summary` gives the result fields both evaluations
    report: ``seconds_per_input``, ``inputs``, ``num_samples``, ``num_steps``, ``sampler``."""

    def __init__(
        self,
        module: PoseModule,
        loader: DataLoader,
        num_samples: int,
        num_steps: int | None,
        sampler: Sampler | None,
        seed: int,
        max_inputs: int | None,
    ) -> None:
        self.module, self.loader, self.num_samples, self.num_steps = module, loader, num_samples, num_steps
        self.sampler, self.seed, self.max_inputs = sampler, seed, max_inputs
        self.seconds = 0.0
        self.count = 0

    def __iter__(self) -> Iterator[tuple[dict[str, torch.Tensor], torch.Tensor]]:
        module, limit = self.module, self.max_inputs
        gen = torch.Generator(device=module.device).manual_seed(int(self.seed))
        for batch in self.loader:
            if limit is not None and self.count >= limit:
                break
            batch = {k: v.to(module.device) for k, v in batch.items() if isinstance(v, torch.Tensor)}
            if limit is not None and self.count + int(batch["pose"].shape[0]) > limit:
                batch = {k: v[: limit - self.count] for k, v in batch.items()}
            start = time.perf_counter()
            x = module.sample(
                batch[module.cond_key], self.num_samples, self.num_steps, sampler=self.sampler, generator=gen
            )
            if x.is_cuda:
                torch.cuda.synchronize(x.device)
            self.seconds += time.perf_counter() - start
            self.count += int(batch["pose"].shape[0])
            yield batch, x

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "seconds_per_input": self.seconds / max(self.count, 1),
            "inputs": self.count,
            "num_samples": int(self.num_samples),
        }
        if isinstance(self.module, PoseRegressionModule):  # one estimate, refined `iterations` times
            return {**out, "num_steps": self.module.iterations, "sampler": "regression"}
        s = self.sampler or self.module.sampler
        steps = self.num_steps if self.num_steps is not None else s.num_steps
        return {
            **out,
            "num_steps": steps if steps is not None else len(s.diffusion.schedule.timesteps(None)),
            "sampler": getattr(s, "name", type(s).__name__),
        }


__all__ = ["ACCELERATION_MODES", "SampledBatches", "accelerated_denoise_fn"]


#: how :func:`accelerated_denoise_fn` runs the denoiser step
ACCELERATION_MODES = ("eager", "compiled", "cudagraphs")


def accelerated_denoise_fn(module: PoseDiffusionModule, mode: str = "eager") -> Any:
    """The ``denoise_fn(x, sigma, cond)`` a sampler calls, run ``mode``: ``eager`` (the module's
    forward), ``compiled`` (``torch.compile`` of the step: one fused graph for the group math and the
    MLP, recompiled per input shape) or ``cudagraphs`` (``torch.compile(mode="reduce-overhead")``:
    the step captured as a CUDA graph once per shape, replayed without Python or launch overhead;
    needs CUDA). The samples are the eager ones up to floating-point reassociation (tested)."""
    if mode not in ACCELERATION_MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of: {', '.join(ACCELERATION_MODES)}")
    if mode == "eager":
        return module.denoise_fn()
    if mode == "cudagraphs" and not torch.cuda.is_available():
        raise ValueError("mode=cudagraphs needs a CUDA device")
    return torch.compile(
        module.forward, mode="reduce-overhead" if mode == "cudagraphs" else None, dynamic=False
    )
