"""Exports against bad input: a tampered export folder never runs code or reads outside itself
(:func:`posediff.models.export.load_exported`), the unrolled step count has a default that finishes and a
bound (:func:`posediff.models.export.unrolled_steps`), and a full disk is one line with nothing left behind
(``posediff export`` through the real CLI in a subprocess).

The attack of the first test is the one a user found: a real ExportedProgram whose weights config marks
one weight as pickled, its bytes replaced by a pickle that creates a sentinel file when unpickled.
``torch.export.load`` runs it (checked, so the test is not vacuous); ``load_exported`` refuses it
without and with ``trust=True``, and the sentinel never appears.
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import resource
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from posediff.cli import config_dir, main
from posediff.config import register_resolvers
from posediff.models.export import (
    DEFAULT_NUM_STEPS,
    ExportedFilesError,
    ExportError,
    export_module,
    load_exported,
    unrolled_steps,
)

POSEDIFF = [sys.executable, "-m", "posediff.cli"]
TOY = ["+experiment=toy_so3", "trainer.max_steps=2", "trainer.val_check_interval=2",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip


def _model(*overrides: str):  # noqa: ANN202 - (module, example condition)
    register_resolvers()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=toy_so3", "denoiser.hidden_dim=16", *overrides])
    torch.manual_seed(0)
    module = instantiate(cfg.module).eval()
    dm = instantiate(cfg.data)
    dm.setup("test")
    return module, next(iter(dm.test_dataloader()))[module.cond_key][:2]


@pytest.fixture(scope="module")
def model():  # noqa: ANN201
    return _model()


@pytest.fixture(scope="module")
def exports(model, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:  # noqa: ANN001
    """A real export of the toy model in each of the two formats torch loads (one step each)."""
    module, example = model
    base = tmp_path_factory.mktemp("exports")
    for fmt in ("torchscript", "exported_program"):
        export_module(module, base / fmt, fmt, example=example, num_steps=1, num_samples=3)
    return {"torchscript": base / "torchscript", "exported_program": base / "exported_program"}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _edit_meta(folder: Path, **changes) -> None:  # noqa: ANN003
    meta = json.loads((folder / "posediff_export.json").read_text())
    for key, value in changes.items():
        if key.startswith("files_"):
            meta["files"][key[len("files_") :]] = value
        else:
            meta[key] = value
    (folder / "posediff_export.json").write_text(json.dumps(meta))


class _Payload:
    """Unpickling it creates ``path`` (an ``open(path, "w")`` call): the proof that a load ran code."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):  # noqa: ANN204
        return (open, (self.path, "w"))


def _pickled_weight(pt2: Path, sentinel: Path) -> None:
    """Edit the real archive ``pt2`` in place: its first weight marked ``use_pickle`` and its bytes a
    pickle of :class:`_Payload` (what ``torch.export.load`` then hands to ``torch.load(weights_only=False)``)."""
    with zipfile.ZipFile(pt2) as z:
        items = [(info, z.read(info.filename)) for info in z.infolist()]
    config_name = next(i.filename for i, _ in items if i.filename.endswith("_weights_config.json"))
    config = json.loads(dict((i.filename, d) for i, d in items)[config_name])
    first = next(iter(config["config"]))
    config["config"][first]["use_pickle"] = True
    weight = config["config"][first]["path_name"]
    with zipfile.ZipFile(pt2, "w", zipfile.ZIP_STORED) as z:
        for info, data in items:
            if info.filename == config_name:
                data = json.dumps(config).encode()
            elif info.filename.endswith(f"/data/weights/{weight}"):
                data = pickle.dumps(_Payload(sentinel))
            z.writestr(info, data)


# ---------------------------------------------------------------------------------------------------
# 1. a tampered export runs nothing
# ---------------------------------------------------------------------------------------------------


def test_a_pt2_with_a_pickled_weight_is_refused_and_its_payload_never_runs(
    exports: dict[str, Path], tmp_path: Path
) -> None:
    folder = _copy(exports["exported_program"], tmp_path / "ep")
    sentinel = tmp_path / "payload_ran"
    _pickled_weight(folder / "encoder.pt2", sentinel)
    probe = tmp_path / "probe.pt2"  # the attack is real: torch's own loader runs it
    shutil.copy(folder / "encoder.pt2", probe)
    try:
        torch.export.load(str(probe))
    except Exception:  # noqa: BLE001, S110 - the payload runs before the load fails on the bad weight
        pass
    assert sentinel.exists(), "the test's payload should run under a plain torch.export.load"
    sentinel.unlink()

    with pytest.raises(ExportedFilesError, match=r"load_exported\(folder, trust=True\)") as e:
        load_exported(folder)
    assert len(str(e.value).splitlines()) == 1 and "torch.export.load unpickles" in str(e.value)
    with pytest.raises(
        ExportedFilesError, match=r"encoder\.pt2 is not a plain torch.export archive.*pickled"
    ):
        load_exported(folder, trust=True)  # trusted, the archive is still inspected first
    assert not sentinel.exists(), "the payload ran"


def test_a_json_switched_to_exported_program_is_refused(exports: dict[str, Path], tmp_path: Path) -> None:
    """The user's attack: a TorchScript export's JSON switched to ``exported_program``, its files
    pointed at ``.pt2`` archives dropped in, one with a pickled weight."""
    folder = _copy(exports["torchscript"], tmp_path / "ts")
    sentinel = tmp_path / "payload_ran"
    for name in ("encoder", "denoiser", "sampler"):
        shutil.copy(exports["exported_program"] / f"{name}.pt2", folder / f"x_{name}.pt2")
    _pickled_weight(folder / "x_encoder.pt2", sentinel)
    _edit_meta(folder, format="exported_program", files_encoder="x_encoder.pt2",
               files_denoiser="x_denoiser.pt2", files_sampler="x_sampler.pt2")  # fmt: skip
    for trust in (False, True):
        with pytest.raises(ExportedFilesError):
            load_exported(folder, trust=trust)
    assert not sentinel.exists(), "the payload ran"


def test_formats_torch_loads_need_trust_and_then_load(model, exports: dict[str, Path]) -> None:  # noqa: ANN001
    module, example = model
    with pytest.raises(ExportedFilesError, match="torch.jit.load runs the TorchScript code"):
        load_exported(exports["torchscript"])
    for fmt, folder in exports.items():  # a genuine archive passes the .pt2 inspection
        meta, run = load_exported(folder, trust=True)
        assert meta["format"] == fmt
        with torch.no_grad():
            torch.testing.assert_close(run["encoder"](example), module.encode(example), atol=1e-5, rtol=1e-5)


@pytest.fixture
def no_loading(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any loader call fails the test: the refusals below come before anything is opened."""

    def boom(*args, **kwargs) -> None:  # noqa: ANN002, ANN003
        raise AssertionError(f"a loader ran on {args[:1]}")

    monkeypatch.setattr(torch.jit, "load", boom)
    monkeypatch.setattr(torch.export, "load", boom)


def _outside(tmp_path: Path, exports: dict[str, Path]) -> Path:
    outside = tmp_path / "elsewhere"
    outside.mkdir(exist_ok=True)
    shutil.copy(exports["torchscript"] / "encoder.pt", outside / "encoder.pt")
    return outside / "encoder.pt"


CONFINEMENT = {
    "dotdot": (lambda f, o: {"files_encoder": "../elsewhere/encoder.pt"}, "not a plain file name"),
    "path_inside": (lambda f, o: {"files_encoder": "./encoder.pt"}, "not a plain file name"),
    "absolute": (lambda f, o: {"files_encoder": str(o)}, "not a plain file name"),
    "symlink_out": (lambda f, o: (f / "link.pt").symlink_to(o) or {"files_encoder": "link.pt"},
                    "leads outside the export folder"),
    "wrong_suffix": (lambda f, o: {"files_encoder": "posediff_export.json"}, "not a .pt file"),
    "missing": (lambda f, o: {"files_encoder": "gone.pt"}, "no such file"),
    "not_a_string": (lambda f, o: {"files_encoder": ["encoder.pt"]}, "not a file name"),
    "unknown_format": (lambda f, o: {"format": "pickle"}, "unknown format 'pickle'"),
    "extra_graph": (lambda f, o: {"files_extra": "encoder.pt"}, "must name exactly the graphs"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(CONFINEMENT))
def test_file_entries_are_confined_to_the_folder(
    case: str, exports: dict[str, Path], tmp_path: Path, no_loading: None
) -> None:
    folder = _copy(exports["torchscript"], tmp_path / "ts")
    edit, message = CONFINEMENT[case]
    _edit_meta(folder, **edit(folder, _outside(tmp_path, exports)))
    for trust in (False, True):  # confinement holds for trusted folders too
        with pytest.raises(ExportedFilesError) as e:
            load_exported(folder, trust=trust)
        assert message in str(e.value) and len(str(e.value).splitlines()) == 1, str(e.value)


def test_no_or_bad_json_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ExportedFilesError, match="no posediff_export.json in"):
        load_exported(tmp_path)
    (tmp_path / "posediff_export.json").write_text("{not json")
    with pytest.raises(ExportedFilesError, match="is not valid JSON"):
        load_exported(tmp_path)


# ---------------------------------------------------------------------------------------------------
# 2. the unrolled step count
# ---------------------------------------------------------------------------------------------------


def test_default_step_count_and_bound(model) -> None:  # noqa: ANN001
    module, _ = model
    levels = module.diffusion.schedule.num_levels
    assert module.sampler.num_steps is None and levels > DEFAULT_NUM_STEPS  # the case that looked hung
    assert unrolled_steps(module.sampler, "onnx") == (DEFAULT_NUM_STEPS, "default")
    assert unrolled_steps(module.sampler, "onnx", 7) == (7, "num_steps")
    with pytest.raises(ExportError, match=r"num_steps=50 would unroll into one onnx graph.*max_unrolled=50"):
        unrolled_steps(module.sampler, "onnx", 50)
    assert unrolled_steps(module.sampler, "onnx", 50, max_unrolled=50) == (50, "num_steps")  # still possible
    assert unrolled_steps(module.sampler, "torchscript", levels) == (levels, "num_steps")  # tracing is fast
    with pytest.raises(ExportError, match=r"num_steps must be in \[1, "):
        unrolled_steps(module.sampler, "torchscript", levels + 1)
    own, _ = _model("sampler.num_steps=3")
    assert unrolled_steps(own.sampler, "onnx") == (3, "sampler")
    many, _ = _model("sampler.num_steps=40")
    with pytest.raises(ExportError, match="the checkpoint's sampler's 40 steps"):
        unrolled_steps(many.sampler, "onnx")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("toy") / "run"
    assert main(["fit", *TOY, f"hydra.run.dir={run}"]) == 0
    return run / "checkpoints" / "last.ckpt"


def _cli(args: list[str], cwd: Path, **kwargs) -> subprocess.CompletedProcess:  # noqa: ANN003
    return subprocess.run([*POSEDIFF, *args, f"hydra.run.dir={cwd / 'hydra'}"], cwd=cwd, capture_output=True,
                          text=True, timeout=600, **kwargs)  # fmt: skip


def _one_line(proc: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr[-3000:]
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("posediff export: "), lines[-20:]
    return lines[0]


def test_cli_prints_the_step_count_and_refuses_too_many(ckpt: Path, tmp_path: Path) -> None:
    proc = _cli(["export", f"ckpt_path={ckpt}", "format=torchscript", f"out={tmp_path / 'ts'}"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (f"posediff export: unrolling {DEFAULT_NUM_STEPS} sampling steps into the torchscript sampler graph "
            "(the default; the checkpoint's sampler sets none); num_steps=N changes it") in proc.stdout  # fmt: skip
    assert (
        json.loads((tmp_path / "ts" / "posediff_export.json").read_text())["num_steps"] == DEFAULT_NUM_STEPS
    )
    proc = _cli(
        ["export", f"ckpt_path={ckpt}", "format=onnx", "num_steps=50", f"out={tmp_path / 'big'}"], tmp_path
    )
    assert "num_steps=50 would unroll into one onnx graph, above max_unrolled=20" in _one_line(proc)
    assert not (tmp_path / "big").exists() and not (tmp_path / "big.partial").exists()


# ---------------------------------------------------------------------------------------------------
# 3. a full disk
# ---------------------------------------------------------------------------------------------------


def _nothing_left(folder: Path) -> None:
    assert not list(folder.iterdir()), sorted(p.name for p in folder.rglob("*"))


def test_full_disk_is_one_line_and_leaves_nothing(ckpt: Path, tmp_path: Path) -> None:
    """A 300 KB tmpfs (the toy's encoder.pt is ~380 KB): ENOSPC, through the real CLI."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command: cannot make a small file system")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(disk)], capture_output=True,
                             text=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"mounting a small tmpfs is not permitted here ({mounted.stderr.strip()[:200]})")
    try:
        proc = _cli(["export", f"ckpt_path={ckpt}", "format=torchscript", "num_steps=2", f"out={disk / 'ts'}"],
                    tmp_path)  # fmt: skip
        line = _one_line(proc)
        assert f"out={disk / 'ts'}: cannot write encoder.pt" in line and "No space left on device" in line, (
            line
        )
        assert f"in {disk / 'ts.partial'}" in line and "free space there or choose another out=" in line, line
        _nothing_left(disk)
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def test_a_write_limit_is_one_line_and_leaves_nothing(ckpt: Path, tmp_path: Path) -> None:
    """The same without privileges: a per-file size limit (RLIMIT_FSIZE; Python ignores SIGXFSZ, so a
    write past it fails with EFBIG) in the CLI's process, for ExportedProgram's files."""
    out = tmp_path / "out"
    out.mkdir()
    limit = 200_000  # above the marker and the JSON, below the toy's .pt2 graphs (~380 KB and up)

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = _cli(["export", f"ckpt_path={ckpt}", "format=exported_program", "num_steps=1", f"out={out / 'ep'}"],
                tmp_path, preexec_fn=small_files)  # fmt: skip
    line = _one_line(proc)
    assert f"out={out / 'ep'}: cannot write encoder.pt2" in line and os.strerror(errno.EFBIG) in line, line
    _nothing_left(out)
