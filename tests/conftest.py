"""Shared pytest setup: offscreen-safe environment, a --device option, a seeded generator."""

import os
import signal

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

# A shell starts a background job (`make test &`, `nohup ... &` in a script) with SIGINT ignored, and
# an ignored signal stays ignored across exec: the Ctrl-C tests' subprocesses would never see their
# SIGINT. Python's own handler here resets to the default in every child the tests start.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


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


@pytest.fixture(scope="session")
def bop_root(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201 - pathlib.Path
    """A small BOP-format dataset made by ``posediff.data.bop.fixture`` (once per test session)."""
    from posediff.data.bop.fixture import make_bop_fixture

    out = tmp_path_factory.mktemp("bop") / "fixture"
    make_bop_fixture(out, seed=0, width=240, height=180, pbr_scenes=2, pbr_images=4, train_views=4,
                     test_scenes=2, test_images=2)  # fmt: skip
    return out
