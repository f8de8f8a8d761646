"""Exact resume: a real ``posediff fit`` killed with SIGKILL after its step-20 ``last.ckpt`` and resumed
from it with ``ckpt_path=`` ends bit-identical to an uninterrupted run (weights, optimizer state,
loss history, metrics.json's loss summary).

The run is the SO(3) toy at a tiny size, with 7 shuffled batches per epoch (``num_workers=0``):
step 20 is mid-epoch (epoch 2, batch 6), and the resumed part crosses three epoch boundaries and
validates every 10 steps. In the killed run the trainer's ProgressLog callback, once the step-20
checkpoint is on disk, writes a marker and waits (it would go on after a minute);
the test then kills it with SIGKILL. The stall is patched in by a ``sitecustomize`` on the killed
run's ``PYTHONPATH``, so all three runs have the same config.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from posediff.data.resumable import ResumableDataLoader

ROOT = Path(__file__).resolve().parents[2]
POSEDIFF = Path(sys.executable).with_name("posediff")

TINY = [
    "+experiment=toy_so3",
    "data.num_train=224",  # 7 batches of 32 per epoch
    "data.batch_size=32",
    "data.num_val_per_shape=2",
    "module.num_noisy=8",
    "denoiser.hidden_dim=16",
    "denoiser.num_frequencies=8",
    "denoiser.time_dim=16",
    "eval.before=false",
    "eval.num_samples=4",
    "eval.num_steps=[2]",
    "eval.samplers=null",
    "trainer.max_steps=60",
    "trainer.val_check_interval=10",
    "trainer.limit_val_batches=2",
    "trainer.log_every_n_steps=5",
    "trainer.enable_progress_bar=false",
    "trainer.callbacks.0.every_n_train_steps=20",  # last.ckpt at steps 20, 40, 60
]

# The killed run's sitecustomize: its config stays the uninterrupted run's (the checkpoint stores it).
STALL = """
import os

if os.environ.get("POSEDIFF_TEST_STALL_AT"):
    import time
    from pathlib import Path

    from posediff.training.callbacks import ProgressLog

    _at, _marker = int(os.environ["POSEDIFF_TEST_STALL_AT"]), Path(os.environ["POSEDIFF_TEST_MARKER"])
    _start = ProgressLog.on_train_batch_start

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        # the first batch after step _at: its checkpoint is on disk; wait a minute, then go on
        if trainer.global_step == _at and not _marker.exists():
            _marker.write_text(str(trainer.global_step))
            time.sleep(60)
        return _start(self, trainer, pl_module, batch, batch_idx)

    ProgressLog.on_train_batch_start = on_train_batch_start
"""


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSEDIFF_TEST_")}
    return dict(env, OMP_NUM_THREADS="1", **extra)


def _fit(run_dir: Path, *extra: str, env: dict[str, str]) -> subprocess.Popen:
    cmd = [str(POSEDIFF), "fit", *TINY, f"hydra.run.dir={run_dir}", *extra]
    log = (run_dir.parent / f"{run_dir.name}.log").open("w")
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)


def _wait(proc: subprocess.Popen, log: Path, timeout: float = 240) -> None:
    assert proc.wait(timeout=timeout) == 0, log.read_text()[-4000:]


@pytest.mark.skipif(not POSEDIFF.exists(), reason="the posediff console script is not installed")
def test_sigkill_and_resume_is_bit_exact(tmp_path: Path) -> None:
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(STALL)
    marker = tmp_path / "stalled"
    full_dir, killed_dir, resumed_dir = tmp_path / "full", tmp_path / "killed", tmp_path / "resumed"

    full = _fit(full_dir, env=_env())
    stall = {"POSEDIFF_TEST_STALL_AT": "20", "POSEDIFF_TEST_MARKER": str(marker)}
    path = os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])
    killed = _fit(killed_dir, env=_env(PYTHONPATH=path, **stall))
    deadline = time.monotonic() + 240
    while not marker.exists():
        assert killed.poll() is None, (tmp_path / "killed.log").read_text()[-4000:]
        assert time.monotonic() < deadline, "the run never reached step 20"
        time.sleep(0.05)
    killed.send_signal(signal.SIGKILL)
    assert killed.wait(timeout=30) == -signal.SIGKILL
    assert not (killed_dir / "metrics.json").exists()
    last = killed_dir / "checkpoints" / "last.ckpt"
    part = torch.load(last, map_location="cpu", weights_only=True)
    assert part["global_step"] == 20
    assert len(part["posediff_loss_history"]) == 20
    loader_state = part["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert loader_state == [{"epoch": 2, "batches": 6, "num_batches": 7}], loader_state

    resumed = _fit(resumed_dir, f"ckpt_path={last}", env=_env())
    _wait(resumed, tmp_path / "resumed.log")
    _wait(full, tmp_path / "full.log")

    a = torch.load(full_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    b = torch.load(resumed_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert a["global_step"] == b["global_step"] == 60
    assert a["state_dict"].keys() == b["state_dict"].keys()
    differ = {k: float((a["state_dict"][k] - b["state_dict"][k]).abs().max()) for k in a["state_dict"]
              if not torch.equal(a["state_dict"][k], b["state_dict"][k])}  # fmt: skip
    assert not differ, f"weights differ after resume: {differ}"
    adam_a, adam_b = a["optimizer_states"][0]["state"], b["optimizer_states"][0]["state"]
    assert adam_a.keys() == adam_b.keys()
    for sa, sb in zip(adam_a.values(), adam_b.values(), strict=True):
        assert all(torch.equal(sa[k], sb[k]) for k in sa), "Adam moments differ"
    assert a["lr_schedulers"] == b["lr_schedulers"]
    assert torch.equal(a["posediff_loss_history"], b["posediff_loss_history"])
    assert len(b["posediff_loss_history"]) == 60
    ta = json.loads((full_dir / "metrics.json").read_text())["train"]
    tb = json.loads((resumed_dir / "metrics.json").read_text())["train"]
    assert tb["steps"] == ta["steps"] == 60
    assert tb["loss_first"] == ta["loss_first"] and tb["loss_last"] == ta["loss_last"], (ta, tb)


class _Items(torch.utils.data.Dataset):
    def __init__(self, n: int) -> None:
        self.n, self.epochs = n, []

    def __len__(self) -> int:
        return self.n

    def set_epoch(self, epoch: int) -> None:
        self.epochs.append(epoch)

    def __getitem__(self, i: int) -> int:
        return i


def _take(loader: ResumableDataLoader, k: int) -> list[list[int]]:
    it = iter(loader)
    return [next(it).tolist() for _ in range(k)]


@pytest.mark.parametrize("num_workers", [0, 2])
def test_loader_state_continues_the_uninterrupted_order(num_workers: int) -> None:
    """Three passes of 5 batches; a copy restored from the state after 2 batches of pass 1 (and one
    restored at the end of a pass) hands out exactly the batches the original would have."""

    def make() -> ResumableDataLoader:
        return ResumableDataLoader(_Items(23), batch_size=4, shuffle=True, seed=3, drop_last=True,
                                   num_workers=num_workers)  # fmt: skip

    ref = make()
    passes = [[b.tolist() for b in ref] for _ in range(3)]
    assert passes[0] != passes[1] and sorted(sum(passes[0], [])) != list(range(20))  # shuffled per pass
    assert ref.dataset.epochs == [0, 1, 2]

    src = make()
    list(src)  # pass 0
    assert _take(src, 2) == passes[1][:2]
    state = src.state_dict()
    assert state == {"epoch": 1, "batches": 2, "num_batches": 5}
    dst = make()
    dst.load_state_dict(state)
    assert [b.tolist() for b in dst] == passes[1][2:]
    assert [b.tolist() for b in dst] == passes[2]

    end = make()
    list(end)
    assert end.state_dict() == {"epoch": 1, "batches": 0, "num_batches": 5}  # a finished pass
    with pytest.raises(ValueError, match="batches"):
        ResumableDataLoader(_Items(40), batch_size=4).load_state_dict(state)
