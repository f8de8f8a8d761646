"""Test-only hook: makes a render stop at a point the test chooses, so its Ctrl-C is not a race.

Only the Ctrl-C tests put this folder on a subprocess's ``PYTHONPATH``; Python then imports this file
at start-up in that process and in every Python process it starts (a ``spawn`` pool's workers, the
resource tracker; a forked worker inherits it). With ``POSEDIFF_TEST_PAUSE_DIR`` set, a process that
has moved ``POSEDIFF_TEST_PAUSE_AFTER`` (default 1) shard files into place pauses when it is about
to move the next one: that shard's bytes are in posediff's temporary file, not yet renamed. It then
writes ``paused-<pid>`` into ``POSEDIFF_TEST_PAUSE_DIR`` and sleeps until a signal ends the sleep:
a SIGINT under Python's default handler raises ``KeyboardInterrupt`` there (a render in one process);
a pool worker ignores SIGINT and sleeps on until its parent terminates it. Without the variable
nothing is changed. The pause is in ``os.replace``, the rename of ``posediff._io.atomic_write_bytes``.
"""

import os
import re
import sys
import time

_PAUSE_DIR = os.environ.get("POSEDIFF_TEST_PAUSE_DIR")

if _PAUSE_DIR:
    _AFTER = int(os.environ.get("POSEDIFF_TEST_PAUSE_AFTER", "1"))
    _SHARD = re.compile(r"shard-\d+\.npz")
    _real_replace = os.replace
    _moved = [0]  # shards this process has moved into place

    def _pause(src: str, dst: str) -> None:
        os.makedirs(_PAUSE_DIR, exist_ok=True)
        flag = os.path.join(_PAUSE_DIR, f"paused-{os.getpid()}")
        with open(flag + ".part", "w") as f:
            f.write(f"{src} -> {dst}\n")
        _real_replace(flag + ".part", flag)
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:  # a SIGINT (default handler) raises KeyboardInterrupt here
            time.sleep(0.05)
        raise RuntimeError(f"test hook: paused before {dst} for 600 s and was never interrupted")

    def _replace(src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202 - os.replace's
        if _SHARD.fullmatch(os.path.basename(os.fspath(dst))):
            if _moved[0] >= _AFTER:
                _pause(os.fspath(src), os.fspath(dst))
            _moved[0] += 1
        return _real_replace(src, dst, *args, **kwargs)

    os.replace = _replace


def _chain() -> None:
    """Run the ``sitecustomize`` this file shadows, if the interpreter has one (a distribution's)."""
    import importlib.machinery
    import importlib.util

    here = os.path.dirname(os.path.abspath(__file__))
    rest = [p for p in sys.path if os.path.abspath(p or os.curdir) != here]
    spec = importlib.machinery.PathFinder.find_spec("sitecustomize", rest)
    if spec is not None and spec.loader is not None:
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)


_chain()
