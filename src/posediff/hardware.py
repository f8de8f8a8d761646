"""What the machine computes fast, detected (never assumed): native bf16 on the CPU or the GPU, and the
training precision that follows from it.

* :func:`native_bf16` — the CPU has bf16 dot-product instructions (AVX512-BF16 or AMX-BF16, read
  from ``/proc/cpuinfo``'s flags) and PyTorch's oneDNN uses them; where that is so, bf16 autocast
  runs the ResNet's convolutions faster than float32 (1.3× a ``quickstart`` step on a 2-core AMD
  EPYC with AVX512-BF16, ``benchmarks/results/train_step_bf16.md``). Without them autocast would
  emulate bf16 and be slower.
* :func:`fast_precision` — Lightning's ``precision`` for a training run: ``"bf16-mixed"`` where the
  accelerator computes bf16 natively (a CUDA GPU with bf16, or such a CPU), else ``"32-true"``. No
  experiment uses it by default (bf16 did not pass the equal-learning check on the CPU,
  ``benchmarks/results/train_step_curve_bf16.json``); a run opts in with
  ``trainer.precision='${posediff.fast_precision:${trainer.accelerator}}'``, and its stored config
  records what that resolved to.
"""

from __future__ import annotations

from pathlib import Path

#: the CPU flags of native bf16 arithmetic (x86: AVX512-BF16 dot products, AMX tiles)
BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU's feature flags (the ``flags`` line of ``/proc/cpuinfo``; empty where there is none)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return frozenset(value.split())
    return frozenset()


def native_bf16(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether this CPU computes bf16 natively: one of :data:`BF16_CPU_FLAGS` and oneDNN's bf16 path."""
    if not any(f in cpu_flags(cpuinfo) for f in BF16_CPU_FLAGS):
        return False
    import torch

    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a build without oneDNN's probe
        return False


def fast_precision(accelerator: str = "auto") -> str:
    """``"bf16-mixed"`` where training runs on an accelerator with native bf16 (a CUDA GPU that
    supports it, or a CPU where :func:`native_bf16`), else ``"32-true"``. ``accelerator``: Lightning's
    (``auto`` picks CUDA when there is one, as the Trainer does)."""
    import torch

    if accelerator in ("auto", "gpu", "cuda") and torch.cuda.is_available():
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "32-true"
    return "bf16-mixed" if native_bf16() else "32-true"


def compile_problem() -> str | None:
    """Why ``torch.compile`` (inductor) cannot run here, or ``None``: on the CPU it needs a C++ compiler."""
    import os
    import shutil

    if not any(shutil.which(c) for c in (os.environ.get("CXX", "g++"), "g++", "clang++", "c++")):
        return "inductor needs a C++ compiler on the CPU and none is on PATH (apt install g++)"
    return None


__all__ = ["BF16_CPU_FLAGS", "compile_problem", "cpu_flags", "fast_precision", "native_bf16"]
