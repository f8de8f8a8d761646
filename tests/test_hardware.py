"""Native-bf16 detection and the training precision it selects (``posediff.hardware``), read from the
CPU's flags — never assumed — and the ``${posediff.fast_precision:}`` resolver the configs use."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from posediff import hardware
from posediff.config import register_resolvers

_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
flags\t\t: fpu sse sse2 avx2 avx512f {extra}
bogomips\t: 5192.26
"""


def _cpuinfo(tmp_path: Path, extra: str) -> Path:
    p = tmp_path / "cpuinfo"
    p.write_text(_CPUINFO.format(extra=extra))
    return p


def test_cpu_flags_reads_the_flags_line(tmp_path: Path) -> None:
    flags = hardware.cpu_flags(_cpuinfo(tmp_path, "avx512_bf16 avx512_vnni"))
    assert {"avx2", "avx512f", "avx512_bf16", "avx512_vnni"} <= flags
    assert "AuthenticAMD" not in flags
    assert hardware.cpu_flags(tmp_path / "missing") == frozenset()


def test_no_bf16_flag_means_no_native_bf16(tmp_path: Path) -> None:
    assert hardware.native_bf16(_cpuinfo(tmp_path, "avx512_vnni")) is False


@pytest.mark.parametrize("flag", hardware.BF16_CPU_FLAGS)
def test_a_bf16_flag_defers_to_onednn(tmp_path: Path, flag: str) -> None:
    """With the flag the answer is oneDNN's own probe (a build without bf16 kernels says no)."""
    expected = bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    assert hardware.native_bf16(_cpuinfo(tmp_path, flag)) is expected


@pytest.mark.parametrize("native", [True, False])
def test_fast_precision_on_the_cpu(monkeypatch: pytest.MonkeyPatch, native: bool) -> None:
    monkeypatch.setattr(hardware, "native_bf16", lambda cpuinfo="/proc/cpuinfo": native)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    want = "bf16-mixed" if native else "32-true"
    assert hardware.fast_precision("cpu") == want
    assert hardware.fast_precision("auto") == want


def test_fast_precision_on_a_gpu_asks_the_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hardware, "native_bf16", lambda cpuinfo="/proc/cpuinfo": False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for supported, want in ((True, "bf16-mixed"), (False, "32-true")):
        monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda s=supported: s)
        assert hardware.fast_precision("auto") == want
        assert hardware.fast_precision("gpu") == want
    assert hardware.fast_precision("cpu") == "32-true"  # a CPU run on a GPU machine asks the CPU


def test_the_resolver_gives_what_the_function_gives() -> None:
    register_resolvers()
    cfg = OmegaConf.create(
        {"trainer": {"accelerator": "cpu", "precision": "${posediff.fast_precision:${trainer.accelerator}}"}}
    )
    assert cfg.trainer.precision == hardware.fast_precision("cpu")
    assert cfg.trainer.precision in ("bf16-mixed", "32-true")
