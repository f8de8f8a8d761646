"""Shared pytest setup: offscreen-safe environment, a --device option, a seeded generator."""

import os

import pytest
import torch

# Set before anything imports OpenGL, and import triton before any GL context exists (importing it
# afterwards segfaults; ../shared/docs/install-notes.md). posediff.data.symsol.render does the same.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("LP_NUM_THREADS", "0")
os.environ.setdefault("MPLBACKEND", "Agg")
try:
    import triton  # noqa: F401
except Exception:  # not installed (CPU-only torch) or broken: nothing to protect against
    pass


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", help="torch device for the contract tests (cpu, cuda)")


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    dev = torch.device(request.config.getoption("--device"))
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    return dev


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)
