"""Checkpoints survive a kill and a full disk (posediff.training.checkpoint_io.AtomicCheckpointIO, the trainer's plugin).

Lightning's TorchCheckpointIO writes a checkpoint to ``tempfile.mkstemp()`` in ``$TMPDIR`` and then
``shutil.move``\\ s it: across filesystems a copy that truncates ``last.ckpt`` first, so a SIGKILL in
the copy leaves a fragment, a full disk a fragment and a traceback, and every kill an orphan in
``$TMPDIR``. These tests hold for any timing: at every moment ``last.ckpt`` is whole.

* a real ``posediff fit`` (a checkpoint every step), ``$TMPDIR`` on a tmpfs and the run on another
  filesystem, SIGKILLed while a save is in progress (polled; whenever it lands, the invariants hold),
  then resumed from its ``last.ckpt``;
* a full disk: an ENOSPC injected into the file write (always), and a real ``posediff fit`` whose
  checkpoint folder is a small tmpfs filled up after its first checkpoint (where ``mount`` is allowed);
* stale temporary files of dead processes go, everything else in the folder stays.
"""

import errno
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch

from posediff.cli import input_error_line
from posediff.training import checkpoint_io
from posediff.training.checkpoint_io import (
    TEMP_PATTERN,
    AtomicCheckpointIO,
    CheckpointWriteError,
    remove_stale_temp_files,
    temp_path,
)

ROOT = Path(__file__).resolve().parents[2]
POSEDIFF = Path(sys.executable).with_name("posediff")
HOST = checkpoint_io._host()

TOY = [
    "+experiment=toy_so3",
    "trainer.enable_progress_bar=false",
    "data.num_train=64",
    "data.batch_size=8",
    "data.num_test_per_shape=1",
    "module.num_noisy=4",
    "eval.before=false",
    "eval.num_samples=2",
    "eval.num_steps=[2]",
    "eval.samplers=null",
    "trainer.val_check_interval=100000",  # last.ckpt only (every step, below)
    "trainer.callbacks.0.every_n_train_steps=1",
]


def _dead_pid() -> int:
    """The id of a process that has exited (reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if TEMP_PATTERN.match(p.name))


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _state(n: int = 1000, value: float = 1.0) -> dict:
    return {"state_dict": {"w": torch.full((n,), value)}, "global_step": int(value)}


# --------------------------------------------------------------------------------------------------
# the CheckpointIO directly
# --------------------------------------------------------------------------------------------------


def test_save_writes_in_the_destination_folder_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A temporary name next to the checkpoint, renamed onto it; $TMPDIR is never written."""
    tmpdir = tmp_path / "tmpdir"
    tmpdir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    renames: list[tuple[str, str]] = []
    real_replace = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (renames.append((str(a), str(b))), real_replace(a, b))[1])
    io = AtomicCheckpointIO()
    target = tmp_path / "run" / "checkpoints" / "last.ckpt"
    io.save_checkpoint(_state(value=1), target)
    io.save_checkpoint(_state(value=2), target)
    assert torch.load(target, weights_only=True)["global_step"] == 2
    assert not _files(tmpdir), "nothing may go through $TMPDIR"
    assert renames == [(str(temp_path(target)), str(target))] * 2
    assert os.listdir(target.parent) == ["last.ckpt"]
    assert TEMP_PATTERN.match(temp_path(target).name)["pid"] == str(os.getpid())
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # the usual permissions, as Lightning's
    with pytest.raises(TypeError, match="storage_options"):
        io.save_checkpoint(_state(), target, storage_options={"x": 1})


def test_disk_full_keeps_the_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ENOSPC in the middle of the write: the earlier checkpoint is intact, no temporary file is left,
    and the error is one line naming the file, the cause and what to do (one line in the CLI too)."""
    io = AtomicCheckpointIO()
    target = tmp_path / "checkpoints" / "last.ckpt"
    io.save_checkpoint(_state(value=1), target)
    before = target.read_bytes()

    real_fdopen = os.fdopen

    class Full:  # a disk with 64 KiB left
        def __init__(self, f):  # noqa: ANN001
            self.f, self.left = f, 65536

        def write(self, data) -> int:  # noqa: ANN001
            n = len(memoryview(data).cast("B"))
            if n > self.left:
                self.f.write(bytes(memoryview(data).cast("B")[: self.left]))
                self.left = 0
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.left -= n
            return self.f.write(data)

        def __getattr__(self, name: str):  # noqa: ANN204
            return getattr(self.f, name)

        def __enter__(self):  # noqa: ANN204
            return self

        def __exit__(self, *exc: object) -> None:
            self.f.close()

    monkeypatch.setattr(checkpoint_io.os, "fdopen", lambda fd, *a, **k: Full(real_fdopen(fd, *a, **k)))
    with pytest.raises(CheckpointWriteError) as info:
        io.save_checkpoint(_state(n=200_000, value=2), target)
    monkeypatch.undo()
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"cannot save checkpoint {target}: no space left on device")
    assert "the previous last.ckpt is unchanged" in message and "free space" in message
    assert f"ckpt_path={target}" in message
    assert isinstance(info.value, OSError) and info.value.errno == errno.ENOSPC
    assert target.read_bytes() == before
    assert torch.load(target, weights_only=True)["global_step"] == 1
    assert os.listdir(target.parent) == ["last.ckpt"]
    # what `posediff fit` prints: Lightning re-raises the callback's exception as it is
    try:
        try:
            raise info.value
        except CheckpointWriteError as e:
            raise RuntimeError("wrapped") from e
    except RuntimeError as wrapped:
        assert input_error_line(wrapped) == message


def test_first_save_failing_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(fd: int) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(checkpoint_io.os, "fsync", fail)
    target = tmp_path / "best.ckpt"
    with pytest.raises(CheckpointWriteError, match=r"best\.ckpt: input/output error \(no earlier best\.ckpt"):
        AtomicCheckpointIO().save_checkpoint(_state(), target)
    assert os.listdir(tmp_path) == []


def test_interrupt_during_save_removes_the_temporary_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C (or a bug) mid-write propagates unchanged, the temporary file goes, the old file stays."""
    io = AtomicCheckpointIO()
    target = tmp_path / "last.ckpt"
    io.save_checkpoint(_state(value=1), target)

    def interrupted(fd: int) -> None:  # the new bytes are in the temporary file by now
        assert any(TEMP_PATTERN.match(n) for n in os.listdir(tmp_path))
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint_io.os, "fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        io.save_checkpoint(_state(value=2), target)
    assert os.listdir(tmp_path) == ["last.ckpt"]
    assert torch.load(target, weights_only=True)["global_step"] == 1


def test_stale_temporary_files_go_and_nothing_else(tmp_path: Path) -> None:
    """On each save (and on resume, in the loaded checkpoint's folder) posediff's temporary files of
    dead processes on this host, and any of its temporary files untouched for an hour, are deleted;
    a live process's, another host's recent one and every other file stay."""
    dead, alive = _dead_pid(), os.getppid()
    keep = [
        f".last.ckpt.posediff-{HOST}-{alive}.tmp",  # a live writer
        f".best.ckpt.posediff-{HOST}-{os.getpid()}.tmp",  # this process
        ".last.ckpt.posediff-otherhost-1.tmp",  # another machine, recent
        ".last.ckpt.tmp",
        f"last.ckpt.{dead}.tmp",
        f".last.ckpt.posediff-{HOST}-{dead}.tmp.bak",
        f".last.ckpt.{dead}.tmp",
        "notes.txt",
    ]
    gone = [f".last.ckpt.posediff-{HOST}-{dead}.tmp", ".best.ckpt.posediff-otherhost-2.tmp"]
    for name in keep + gone:
        (tmp_path / name).write_bytes(b"x" * 10)
    old = time.time() - 2 * checkpoint_io.STALE_AFTER_S
    os.utime(tmp_path / gone[1], (old, old))
    (tmp_path / f".x.posediff-{HOST}-{dead}.tmp").mkdir()  # a folder is never deleted
    keep.append(f".x.posediff-{HOST}-{dead}.tmp")

    AtomicCheckpointIO().save_checkpoint(_state(), tmp_path / "last.ckpt")
    assert sorted(os.listdir(tmp_path)) == sorted([*keep, "last.ckpt"])

    (tmp_path / gone[0]).write_bytes(b"x")  # a killed run's leftover, found when resuming from it
    ckpt = AtomicCheckpointIO().load_checkpoint(tmp_path / "last.ckpt", weights_only=True)
    assert ckpt["global_step"] == 1
    assert sorted(os.listdir(tmp_path)) == sorted([*keep, "last.ckpt"])
    assert remove_stale_temp_files(tmp_path / "missing") == []


def test_remove_checkpoint(tmp_path: Path) -> None:
    io = AtomicCheckpointIO()
    io.save_checkpoint(_state(), tmp_path / "best.ckpt")
    io.remove_checkpoint(tmp_path / "best.ckpt")
    io.remove_checkpoint(tmp_path / "best.ckpt")  # already gone: fine
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------------------------------
# real `posediff fit` runs
# --------------------------------------------------------------------------------------------------


def _env(tmpdir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSEDIFF_TEST_")}
    return dict(env, TMPDIR=str(tmpdir), OMP_NUM_THREADS="1")


def _fit(run: Path, *extra: str, env: dict[str, str], log: Path) -> subprocess.Popen:
    cmd = [str(POSEDIFF), "fit", *TOY, f"hydra.run.dir={run}", *extra]
    out = log.open("w")
    err = log.with_suffix(".err").open("w")
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=err)


def _log(log: Path) -> str:
    texts = [p.read_text()[-3000:] for p in (log, log.with_suffix(".err")) if p.exists()]
    return "\n".join(texts)


def _mount_tmpfs(mnt: Path, size: str) -> str | None:
    """Mount a tmpfs of ``size`` at ``mnt`` (made); why not, or ``None`` once mounted."""
    mnt.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True,
                           text=True, timeout=30)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"cannot mount a tmpfs here ({e})"
    return None if r.returncode == 0 else f"cannot mount a tmpfs here: {r.stderr.strip() or r.returncode}"


def _umount(mnt: Path) -> None:
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


@pytest.fixture
def tmpfs_tmpdir(tmp_path: Path):  # noqa: ANN201 - Path
    """A private $TMPDIR on a tmpfs (in /dev/shm, else a tmpfs mounted for it), on another filesystem
    than ``tmp_path`` (the run folder)."""
    import shutil

    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK) and shm.stat().st_dev != tmp_path.stat().st_dev:
        folder = Path(tempfile.mkdtemp(prefix="posediff-test-", dir=shm))
        try:
            yield folder
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return
    mnt = tmp_path / "tmpfs"
    why = _mount_tmpfs(mnt, "256m")
    if why is not None:
        pytest.skip(f"no tmpfs on another filesystem than the run folder for $TMPDIR (/dev/shm: none or the "
                    f"same device; {why})")  # fmt: skip
    try:
        yield mnt
    finally:
        _umount(mnt)


@pytest.mark.skipif(not POSEDIFF.exists(), reason="the posediff console script is not installed")
def test_sigkill_during_save_across_filesystems_then_resume(tmp_path: Path, tmpfs_tmpdir: Path) -> None:
    """SIGKILL while a 23 MB checkpoint is being saved ($TMPDIR a tmpfs, the run on another device):
    last.ckpt loads whole, $TMPDIR holds no orphan, and resuming from last.ckpt (same run folder)
    finishes and leaves no stale temporary file."""
    run = tmp_path / "run"
    ckpts = run / "checkpoints"
    big = ["denoiser.hidden_dim=512"]
    killed = _fit(run, "trainer.max_steps=100000", *big, env=_env(tmpfs_tmpdir), log=tmp_path / "killed.log")
    deadline = time.monotonic() + 120
    while not (ckpts / "last.ckpt").exists():  # the first checkpoint
        assert killed.poll() is None, _log(tmp_path / "killed.log")
        assert time.monotonic() < deadline, "no checkpoint was written"
        time.sleep(0.01)
    deadline = time.monotonic() + 20  # then a moment while a save is in progress (or, failing that, any)
    while time.monotonic() < deadline:
        if _files(tmpfs_tmpdir) or any(TEMP_PATTERN.match(n) for n in os.listdir(ckpts)):
            break
        time.sleep(0.001)
    killed.send_signal(signal.SIGKILL)
    assert killed.wait(timeout=30) == -signal.SIGKILL

    assert not _files(tmpfs_tmpdir), f"orphans in $TMPDIR: {_files(tmpfs_tmpdir)}"
    last = ckpts / "last.ckpt"
    step = torch.load(last, map_location="cpu", weights_only=True)["global_step"]
    assert step >= 1
    # what a kill mid-save leaves (planted when the kill did not land in a save), and a file of someone else's
    orphan = ckpts / f".last.ckpt.posediff-{HOST}-{killed.pid}.tmp"
    if not _temps(ckpts):
        orphan.write_bytes(b"PK\x03\x04 half a checkpoint")
    (ckpts / "notes.txt").write_text("mine")

    resumed = _fit(run, f"trainer.max_steps={step + 2}", f"ckpt_path={last}", *big, env=_env(tmpfs_tmpdir),
                   log=tmp_path / "resumed.log")  # fmt: skip
    assert resumed.wait(timeout=180) == 0, _log(tmp_path / "resumed.log")
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == step + 2
    assert _temps(ckpts) == [], "the killed run's temporary file should be gone"
    assert (ckpts / "notes.txt").read_text() == "mine"
    assert not _files(tmpfs_tmpdir)


@pytest.fixture
def small_tmpfs(tmp_path: Path):  # noqa: ANN201 - Path
    """A 6 MiB tmpfs mounted at ``tmp_path/disk`` (skipped where mount is not permitted)."""
    mnt = tmp_path / "disk"
    why = _mount_tmpfs(mnt, "6m")
    if why is not None:
        pytest.skip(why)
    try:
        yield mnt
    finally:
        _umount(mnt)


@pytest.mark.skipif(not POSEDIFF.exists(), reason="the posediff console script is not installed")
def test_real_full_disk_during_fit(tmp_path: Path, small_tmpfs: Path) -> None:
    """The checkpoint folder (a small tmpfs; the run folder is on disk) fills up after the first
    checkpoint: the run stops with one line naming the file and the cause, last.ckpt is the earlier
    one, whole, and no temporary file is left."""
    ckpts = small_tmpfs
    log = tmp_path / "fit.log"
    on_disk = [f"trainer.callbacks.{i}.dirpath={ckpts}" for i in (0, 1)]  # last.ckpt, best.ckpt
    proc = _fit(tmp_path / "run", "trainer.max_steps=100000", "denoiser.hidden_dim=16", *on_disk,
                env=_env(tmp_path), log=log)  # fmt: skip
    deadline = time.monotonic() + 120
    while not (ckpts / "last.ckpt").exists():
        assert proc.poll() is None, _log(log)
        assert time.monotonic() < deadline, "no checkpoint was written"
        time.sleep(0.01)
    with (ckpts / "filler").open("wb", buffering=0) as f:  # someone else's file takes the rest of the disk
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError as e:
            assert e.errno == errno.ENOSPC
    try:
        rc = proc.wait(timeout=90)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail("the run went on with a full checkpoint disk: " + _log(log))
    err = log.with_suffix(".err").read_text()
    assert rc == 2, _log(log)
    assert "Traceback" not in err, err[-3000:]
    lines = [ln for ln in err.splitlines() if "cannot save checkpoint" in ln]
    assert len(lines) == 1, err[-3000:]
    assert lines[0].startswith(f"posediff fit: cannot save checkpoint {ckpts}/"), lines[0]
    assert ": no space left on device (" in lines[0] and "free space" in lines[0]
    for name in ("last.ckpt", "best.ckpt"):
        if (ckpts / name).exists():
            assert torch.load(ckpts / name, map_location="cpu", weights_only=True)["global_step"] >= 1
    assert _temps(ckpts) == []
    assert sorted(os.listdir(ckpts)) in (["filler", "last.ckpt"], ["best.ckpt", "filler", "last.ckpt"])
