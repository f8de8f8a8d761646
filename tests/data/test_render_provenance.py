"""A rendered SYMSOL split can be trusted: every shard records what it was rendered from, a resumed
render and the reader check it; bad options write nothing; a bad meta.json or a damaged shard is
one line naming the file; Ctrl-C leaves only whole shards and one traceback."""

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from torch.utils.data import DataLoader

from posediff.data.symsol import SymsolDataModule, SymsolRenderer, SymsolShards, render_dataset
from posediff.data.symsol import shards as shards_module
from posediff.data.symsol.datamodule import SymsolShardDataset
from posediff.data.symsol.shards import (
    CorruptShardError,
    MetaFileError,
    ProvenanceError,
    ShardError,
    write_npz,
)

# 2 shapes × 3 poses at 16 px, shards of 4: two shards (4 + 2 samples), a few ms to render
KW = dict(
    dataset="symsolt",
    variant="uniform",
    split="test",
    n_per_shape=3,
    image_size=16,
    shapes=["tet", "cube"],
    shard_size=4,
    progress=False,
)


def _render(out: Path, **over) -> Path:
    render_dataset(out, **{**KW, **over})
    return out / KW["split"]


def _one_line(e: pytest.ExceptionInfo) -> str:
    text = str(e.value)
    assert "\n" not in text and text.strip(), f"not one line: {text!r}"
    return text


# ----------------------------------------------------------------------------- resume checks shards
@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("seed", 1),
        ("image_size", 24),
        ("n_per_shape", 4),
        ("shard_size", 3),
        ("variant", "edge"),
        ("shapes", ["tet", "icosa"]),
    ],
)
def test_resume_without_meta_refuses_shards_of_another_render(tmp_path: Path, field: str, value) -> None:  # noqa: ANN001
    split = _render(tmp_path)
    (split / "meta.json").unlink()
    index = (split / "index.npz").read_bytes()
    with pytest.raises(ProvenanceError) as e:
        _render(tmp_path, **{field: value})
    line = _one_line(e)
    assert "shard-00000.npz" in line and f"{field} " in line, line
    assert "render into a new out= folder or delete" in line
    assert isinstance(e.value, ValueError)
    # nothing was written: the shards, the index and the missing meta.json are as they were
    assert not (split / "meta.json").exists()
    assert (split / "index.npz").read_bytes() == index
    # the original render resumes: nothing to render, and the split reads back
    again = render_dataset(tmp_path, **KW)
    assert again.rendered == 0 and len(SymsolShards(tmp_path, split="test")) == 6


def test_resume_refuses_shards_whose_poses_differ(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    split = _render(tmp_path)
    (split / "meta.json").unlink()
    real = shards_module.sample_poses

    def shifted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 — the same settings, other poses
        p = real(*args, **kwargs)
        return type(p)(p.shape_id, p.R, p.t + 1e-9)

    monkeypatch.setattr(shards_module, "sample_poses", shifted)
    with pytest.raises(ProvenanceError, match=r"shard-00000\.npz .*poses_sha256") as e:
        _render(tmp_path)
    _one_line(e)


def test_resume_refuses_old_shards_without_provenance(tmp_path: Path) -> None:
    split = _render(tmp_path)
    (split / "meta.json").unlink()
    with np.load(split / "shard-00001.npz") as z:  # the shard as posediff-symsol/1 wrote it
        write_npz(split / "shard-00001.npz", {k: z[k] for k in ("rgb", "depth", "index")})
    with pytest.raises(ProvenanceError) as e:
        _render(tmp_path)
    line = _one_line(e)
    assert "shard-00001.npz records no provenance" in line and "new out= folder" in line
    assert not (split / "meta.json").exists()


def test_old_format_meta_is_refused_on_resume_and_by_the_reader(tmp_path: Path) -> None:
    split = _render(tmp_path)
    meta = json.loads((split / "meta.json").read_text())
    meta["format"] = "posediff-symsol/1"
    for key in ("renderer", "poses_sha256"):
        del meta[key]
    (split / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(MetaFileError) as e:
        _render(tmp_path)
    assert "meta.json is from an older posediff" in _one_line(e) and "new out= folder" in str(e.value)
    with pytest.raises(MetaFileError, match="meta.json is from an older posediff") as e:
        SymsolShards(tmp_path, split="test")
    _one_line(e)


def test_stray_shard_beyond_the_render_is_refused(tmp_path: Path) -> None:
    split = _render(tmp_path, n_per_shape=6)  # 12 samples: 3 shards
    (split / "meta.json").unlink()
    for k in (0, 1):
        (split / f"shard-0000{k}.npz").unlink()
    with pytest.raises(ProvenanceError) as e:  # 6 samples want 2 shards; shard 2 is of the other render
        _render(tmp_path)
    assert "shard-00002.npz is not part of this render" in _one_line(e)


# ----------------------------------------------------------------------------- the reader checks shards
def test_reader_refuses_shards_index_or_meta_of_another_render(tmp_path: Path) -> None:
    a, b = _render(tmp_path / "a"), _render(tmp_path / "b", seed=1)
    assert len(SymsolShards(tmp_path / "a", split="test")) == 6

    # one shard of seed 1 among those of seed 0
    mixed = tmp_path / "mixed" / "test"
    shutil.copytree(a, mixed)
    shutil.copy(b / "shard-00001.npz", mixed / "shard-00001.npz")
    with pytest.raises(ProvenanceError) as e:
        SymsolShards(mixed.parent, split="test")
    line = _one_line(e)
    assert "shard-00001.npz does not belong" in line and "seed 1 in the shard, 0 in meta.json" in line
    assert "render the split again into a new folder" in line

    # meta.json and index.npz of seed 1 next to the shards of seed 0 (the resumed-render accident)
    swapped = tmp_path / "swapped" / "test"
    shutil.copytree(a, swapped)
    for name in ("meta.json", "index.npz"):
        shutil.copy(b / name, swapped / name)
    with pytest.raises(ProvenanceError, match=r"shard-00000\.npz does not belong .*seed 0 in the shard") as e:
        SymsolShards(swapped.parent, split="test")
    _one_line(e)
    dm = SymsolDataModule(
        "symsolt", "uniform", root=str(swapped.parent), image_size=16, shapes=["tet", "cube"]
    )
    with pytest.raises(ValueError, match="does not belong"):
        dm.setup("test")

    # an index.npz of other poses than meta.json records
    other_index = tmp_path / "index" / "test"
    shutil.copytree(a, other_index)
    shutil.copy(b / "index.npz", other_index / "index.npz")
    with pytest.raises(ProvenanceError, match=r"index\.npz holds other poses than .*meta\.json") as e:
        SymsolShards(other_index.parent, split="test")
    _one_line(e)


def test_load_shard_checks_the_shard_it_loads(tmp_path: Path) -> None:
    a, b = _render(tmp_path / "a"), _render(tmp_path / "b", seed=1)
    ds = SymsolShards(tmp_path / "a", split="test")
    shutil.copy(b / "shard-00000.npz", a / "shard-00000.npz")  # replaced after the split was opened
    with pytest.raises(ProvenanceError, match=r"shard-00000\.npz does not belong"):
        ds.load_shard(0)


# ----------------------------------------------------------------------------- options checked first
@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("image_size", -5),
        ("image_size", 0),
        ("image_size", 4),
        ("n_per_shape", 0),
        ("n_per_shape", -1),
        ("shard_size", 0),
        ("workers", -1),
        ("seed", -1),
    ],
)
def test_bad_options_write_nothing(tmp_path: Path, key: str, value: int) -> None:
    with pytest.raises(ValueError, match=rf"^{key}={value} is invalid: give an integer of at least") as e:
        render_dataset(tmp_path / "ds", **{**KW, key: value})
    _one_line(e)
    assert not (tmp_path / "ds").exists(), "nothing may be written for invalid options"
    assert render_dataset(tmp_path / "ds", **KW).rendered == 6  # the corrected run is not refused


def test_cli_bad_image_size_then_the_corrected_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from posediff.cli import main

    out = tmp_path / "ds"
    args = ["data", "render", "dataset=symsol", "split=test", "n_per_shape=1", "progress=false", f"out={out}"]
    assert main([*args, "image_size=-5"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err == "posediff data render: image_size must be a whole number in [8, 4096], got -5 (image_size=...)"
    )
    assert not out.exists()
    assert main([*args, "image_size=16"]) == 0
    assert "5 images in" in capsys.readouterr().out


# ----------------------------------------------------------------------------- meta.json
BAD_META = {
    "a list": "[]",
    "a string": '"meta"',
    "invalid JSON": '{"format": ',
    "an empty object": "{}",
    "missing keys": json.dumps({"format": "posediff-symsol/2", "dataset": "symsolt"}),
}


@pytest.mark.parametrize("kind", sorted(BAD_META))
def test_bad_meta_json_is_one_line_on_resume_and_when_read(tmp_path: Path, kind: str) -> None:
    split = _render(tmp_path)
    meta = split / "meta.json"
    meta.write_text(BAD_META[kind])
    with pytest.raises(MetaFileError) as e:
        _render(tmp_path)
    line = _one_line(e)
    assert str(meta) in line and "render into a new out= folder or delete" in line, line
    assert meta.read_text() == BAD_META[kind], "the refused resume must not rewrite meta.json"
    with pytest.raises(MetaFileError) as e:
        SymsolShards(tmp_path, split="test")
    line = _one_line(e)
    assert str(meta) in line and "render the split again into a new folder" in line, line
    dm = SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=16, shapes=["tet", "cube"])
    with pytest.raises(ValueError, match="meta.json"):
        dm.setup("test")


# ----------------------------------------------------------------------------- corrupt shards
@pytest.mark.parametrize("damage", ["truncated", "random bytes"])
def test_corrupt_shard_is_one_line_when_the_split_is_opened(tmp_path: Path, damage: str) -> None:
    split = _render(tmp_path)
    shard = split / "shard-00001.npz"
    data = shard.read_bytes()
    shard.write_bytes(
        data[: len(data) // 2] if damage == "truncated" else np.random.default_rng(0).bytes(len(data))
    )
    with pytest.raises(CorruptShardError) as e:
        SymsolShards(tmp_path, split="test")
    line = _one_line(e)
    assert f"corrupt shard {shard} (" in line and "render again" in line
    assert isinstance(e.value, ValueError) and isinstance(e.value, RuntimeError)
    dm = SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=16, shapes=["tet", "cube"])
    with pytest.raises(ValueError, match=f"corrupt shard {shard}"):
        dm.setup("test")
    # a resumed render names it too, and renders it again once it is deleted
    with pytest.raises(CorruptShardError, match=f"corrupt shard {shard}"):
        _render(tmp_path)
    shard.unlink()
    assert render_dataset(tmp_path, **KW).rendered == 2


def _damage_member(shard: Path, member: str) -> None:
    """Flip bytes inside ``member``'s compressed data; the zip directory stays intact."""
    with zipfile.ZipFile(shard) as zf:
        info = zf.getinfo(member)
    data = bytearray(shard.read_bytes())
    header = info.header_offset
    name_len, extra_len = (
        int.from_bytes(data[header + 26 : header + 28], "little"),
        int.from_bytes(data[header + 28 : header + 30], "little"),
    )
    start = header + 30 + name_len + extra_len
    for i in range(start + info.compress_size // 3, start + info.compress_size // 3 + 8):
        data[i] ^= 0xFF
    shard.write_bytes(bytes(data))


@pytest.mark.parametrize("num_workers", [0, 1])
def test_shard_damaged_inside_surfaces_while_iterating_as_one_line(tmp_path: Path, num_workers: int) -> None:
    split = _render(tmp_path)
    shard = split / "shard-00001.npz"
    _damage_member(shard, "rgb.npy")
    ds = SymsolShards(tmp_path, split="test")  # the zip directory and provenance are intact
    loader = DataLoader(
        SymsolShardDataset(ds, shuffle=False),
        batch_size=2,
        num_workers=num_workers,
        timeout=120 if num_workers else 0,
    )
    with pytest.raises(CorruptShardError) as e:
        list(loader)
    line = _one_line(e)
    assert line.startswith(f"corrupt shard {shard} (") and "render again" in line
    if num_workers:
        assert "DataLoader worker" in (e.value.worker_traceback or "")


def test_shard_errors_survive_pickling_and_torch_rewrapping() -> None:
    err = CorruptShardError("corrupt shard /x/shard-00003.npz (BadZipFile: bad); delete it")
    again = pickle.loads(pickle.dumps(err))
    assert type(again) is CorruptShardError and str(again) == str(err)
    # what torch's ExceptionWrapper.reraise passes when the error came from a worker
    wrapped = (
        "Caught CorruptShardError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
        '  File "x.py", line 1, in <module>\n'
        f"posediff.data.symsol.shards.CorruptShardError: {err}\n"
    )
    assert str(CorruptShardError(wrapped)) == str(err)
    assert issubclass(ShardError, ValueError)


# ----------------------------------------------------------------------------- Ctrl-C
def test_interrupt_in_process_leaves_only_whole_shards(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real, calls = SymsolRenderer.render, [0]

    def render(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        calls[0] += 1
        if calls[0] == 7:  # inside the second shard
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(SymsolRenderer, "render", render)
    with pytest.raises(KeyboardInterrupt):
        _render(tmp_path, n_per_shape=6)
    split = tmp_path / "test"
    assert sorted(p.name for p in split.glob("shard-*.npz")) == ["shard-00000.npz"]
    assert not list(split.glob(".*.tmp"))
    assert json.loads((split / "meta.json").read_text())["complete"] is False
    monkeypatch.setattr(SymsolRenderer, "render", real)
    assert render_dataset(tmp_path, **{**KW, "n_per_shape": 6}).rendered == 8
    assert len(SymsolShards(tmp_path, split="test")) == 12


@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_in_process_is_taken_between_images(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, presses: int
) -> None:
    """A real SIGINT inside the renderer: the first lets the image finish (then the render stops
    before the next one); a second stops at once."""
    real, calls, finished = SymsolRenderer.render, [0], []

    def render(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        calls[0] += 1
        if calls[0] == 7:  # inside the second shard
            for _ in range(presses):
                os.kill(os.getpid(), signal.SIGINT)
            finished.append(True)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(SymsolRenderer, "render", render)
    with pytest.raises(KeyboardInterrupt):
        _render(tmp_path, n_per_shape=6)
    assert calls[0] == 7 and finished == ([True] if presses == 1 else [])
    split = tmp_path / "test"
    assert sorted(p.name for p in split.glob("shard-*.npz")) == ["shard-00000.npz"]
    assert not list(split.glob(".*.tmp"))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


#: tests/_interrupt_hooks/sitecustomize.py: pauses a subprocess (and its workers) before a shard's rename
HOOKS = Path(__file__).resolve().parents[1] / "_interrupt_hooks"


def _paused_render_env(flags: Path, after: int = 1) -> dict[str, str]:
    """The environment of a render whose every process pauses once it has written ``after`` shards,
    with its next shard in a temporary file, and writes ``flags/paused-<pid>`` (the hook's docstring)."""
    pythonpath = os.pathsep.join([str(HOOKS), *filter(None, [os.environ.get("PYTHONPATH")])])
    return {
        **os.environ,
        "PYTHONPATH": pythonpath,
        "POSEDIFF_TEST_PAUSE_DIR": str(flags),
        "POSEDIFF_TEST_PAUSE_AFTER": str(after),
    }


def test_ctrl_c_with_a_process_pool_leaves_whole_shards_and_one_traceback(tmp_path: Path) -> None:
    """Ctrl-C in a terminal sends SIGINT to the whole process group: the parent and its workers.

    Not a race with the render: each of the two workers writes one shard, then pauses with its next
    shard in a temporary file (tests/_interrupt_hooks), and the SIGINTs come once both have paused."""
    script = textwrap.dedent(
        """
        import sys
        from posediff.data.symsol.shards import render_dataset
        render_dataset(sys.argv[1], dataset="symsolt", split="train", n_per_shape=300, image_size=32,
                       shard_size=10, workers=2, progress=False)
        """
    )
    out, flags = tmp_path / "ds", tmp_path / "paused"
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_paused_render_env(flags),
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    split = out / "train"
    try:
        deadline = time.monotonic() + 240
        while len(list(flags.glob("paused-*"))) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is not None:
            pytest.fail(f"the render ended before both workers paused:\n{proc.communicate()[1][-3000:]}")
        paused = sorted(p.name for p in flags.glob("paused-*"))
        assert len(paused) == 2, f"after 240 s, paused: {paused} (the hook pauses in os.replace)"
        # where the render stands: two whole shards, and the next shard of each worker half done
        assert len(list(split.glob("shard-*.npz"))) == 2 and len(list(split.glob(".*.tmp"))) == 2
        # the workers first (in a terminal the order is not fixed): they must ignore it and go on
        for pid in _children(proc.pid):
            os.kill(pid, signal.SIGINT)
        time.sleep(1.0)
        assert proc.poll() is None, "a worker's Ctrl-C must not end the render"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode in (-signal.SIGINT, 130, 1), err[-3000:]
    # the parent's KeyboardInterrupt, once; no traceback of a worker ("Process SpawnPoolWorker-1: …")
    assert err.rstrip().endswith("KeyboardInterrupt"), err[-3000:]
    assert err.splitlines().count("KeyboardInterrupt") == 1 and "PoolWorker" not in err, err[-3000:]
    shards = sorted(split.glob("shard-*.npz"))
    assert len(shards) == 2 < 150, "interrupted part way: the shards written before the pause, no more"
    assert not list(split.glob(".*.tmp")), "temporary files of the terminated workers are removed"
    for shard in shards:  # every shard on disk is whole
        with np.load(shard) as z:
            assert z["rgb"].shape == (10, 32, 32, 3) and z["depth"].shape == (10, 32, 32)
    assert json.loads((split / "meta.json").read_text())["complete"] is False
