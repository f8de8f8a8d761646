"""Bad input through the real CLI: each case runs ``posediff ...`` in a subprocess and must get one line
on stderr (``posediff <command>: ...``), a non-zero exit (2 for bad input, 130 for Ctrl-C), no
traceback, and leave every file that existed before untouched.

The table is docs/reliability.md's. The subprocesses run two at a time (each starts
torch and Lightning, a few seconds); the shared inputs — a two-step toy checkpoint, a tiny BOP
fixture, a tiny SYMSOL-T render — are made in-process once.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from posediff.cli import main

POSEDIFF = [sys.executable, "-m", "posediff.cli"]

TOY = ["+experiment=toy_so3", "trainer.max_steps=2", "trainer.val_check_interval=2",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip
BOP = ["+experiment=tless_se3", "encoder.arch=resnet18", "encoder.out_dim=16", "denoiser.hidden_dim=16",
       "data.image_size=32", "data.batch_size=2", "data.num_workers=0", "module.num_noisy=4",
       "trainer.precision=32-true", "trainer.enable_progress_bar=false", "trainer.max_steps=1",
       "eval.before=false", "eval.num_steps=[2]", "eval.num_samples=1"]  # fmt: skip
SYMSOL = ["+experiment=quickstart", "data.image_size=32", "data.shapes=[tet,cube]", "data.batch_size=2",
          "data.n_per_shape_test=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "encoder.out_dim=16",
          "encoder.crop_size=null", "encoder.depth_cue=null", "trainer.max_steps=2", "trainer.enable_progress_bar=false",
          "eval.before=false", "eval.num_samples=1", "eval.num_steps=[2]"]  # fmt: skip
OFFICIAL = ["+experiment=symsol_so3", "encoder.arch=resnet18", "encoder.out_dim=16", "denoiser.hidden_dim=16",
            "data=symsol_official", "data.image_size=32", "data.batch_size=2", "data.num_workers=0",
            "data.shapes=[tet,cube]", "module.num_noisy=4", "trainer.max_steps=1", "trainer.precision=32-true",
            "trainer.enable_progress_bar=false", "eval.before=false", "eval.num_samples=1", "eval.num_steps=[2]",
            "eval.log_likelihood=false"]  # fmt: skip
OFFICIAL_T = [*OFFICIAL[:4], "data=symsolt_official", "group=se3", *OFFICIAL[5:]]
RENDER = ["data", "render", "dataset=symsolt", "image_size=32", "n_per_shape=2", "shapes=[tet,cube]",
          "shard_size=2", "progress=false"]  # fmt: skip


@dataclass
class Env:
    """The shared inputs (made once) and the case's own folder."""

    ckpt: Path
    bop: Path
    symsol: Path
    image_ckpt: Path  # a 2-step image model on the symsol renders
    dir: Path = field(default_factory=Path)

    def copy_of(self, src: Path, name: str) -> Path:
        dst = self.dir / name
        shutil.copytree(src, dst)
        return dst


@dataclass
class Case:
    id: str
    gets: str  # what the user gets (docs/reliability.md's right column)
    args: Callable[[Env], list[str]]
    message: str  # a part of the one line
    code: int = 2
    interrupt: Callable[[Env], bool] | None = None  # send SIGINT once this holds
    lines: int = 1  # lines on stderr (a sweep: one per failed job, then the count)
    after: Callable[[Env], None] | None = None  # extra checks on the case folder
    environ: Callable[[Env], dict[str, str]] | None = None  # extra environment variables
    stdout: str = "pipe"  # "pipe"; "closed": a reader that has gone (`| head -1`); "full": > /dev/full
    file_limit: int | None = None  # a largest file size in bytes (RLIMIT_FSIZE): a disk that fills up


def _tampered(env: Env) -> Path:
    ckpt = torch.load(env.ckpt, weights_only=True)
    cfg = copy.deepcopy(ckpt["posediff_config"])
    sentinel = env.dir / "precious.txt"
    cfg["data"]["seed"] = {"_target_": "builtins.min", "_args_": [[0, {"_target_": "builtins.open",
                           "_args_": [str(sentinel), "w"]}]]}  # fmt: skip
    ckpt["posediff_config"] = cfg
    torch.save(ckpt, env.dir / "tampered.ckpt")
    return env.dir / "tampered.ckpt"


def _write(env: Env, name: str, data: bytes) -> Path:
    (env.dir / name).write_bytes(data)
    return env.dir / name


def _png(env: Env, name: str, array: np.ndarray, mode: str | None = None) -> Path:
    from PIL import Image

    Image.fromarray(array, mode=mode).save(env.dir / name)
    return env.dir / name


def _truncated_png(env: Env) -> Path:
    p = _png(env, "full.png", (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8))
    return _write(env, "truncated.png", p.read_bytes()[:300])


def _bomb(env: Env) -> Path:
    from PIL import Image

    Image.new("1", (8000, 8000)).save(env.dir / "bomb.png")  # 64 megapixels in a few kB
    return env.dir / "bomb.png"


def _bop_without(env: Env, pattern: str) -> Path:
    root = env.copy_of(env.bop, "bop")
    victim = sorted(root.glob(pattern))[0]
    victim.unlink()
    return root


def _bop_resized_test_image(env: Env) -> Path:
    from PIL import Image

    root = env.copy_of(env.bop, "bop")
    victim = sorted(root.glob("test_primesense/*/rgb/*.png"))[0]
    Image.open(victim).resize((50, 40)).save(victim)
    return root


def _bop_without_diameter(env: Env) -> Path:
    import json

    root = env.copy_of(env.bop, "bop")
    info_path = root / "models_eval" / "models_info.json"
    info = json.loads(info_path.read_text())
    del info["2"]["diameter"]
    info_path.write_text(json.dumps(info))
    return root


def _symsol_corrupt_shard(env: Env) -> Path:
    root = env.copy_of(env.symsol, "symsol")
    victim = sorted((root / "train").glob("*.npz"))[0]
    victim.write_bytes(os.urandom(200))
    return root


def _symsol_meta(env: Env, text: str) -> Path:
    root = env.copy_of(env.symsol, "symsol")
    (root / "train" / "meta.json").write_text(text)
    return root


def _symsol_without_meta(env: Env) -> Path:
    root = env.copy_of(env.symsol, "symsol")
    (root / "train" / "meta.json").unlink()
    return root


def _text(path: Path) -> str:
    return path.read_text() if path.is_file() else ""


def _no_metrics(env: Env) -> None:
    assert not list(env.dir.rglob("metrics.json")), "nothing is written for bad input"


def _no_checkpoints(env: Env) -> None:
    assert not list(env.dir.rglob("*.ckpt*")) or all(
        p.name == "tampered.ckpt" for p in env.dir.rglob("*.ckpt")
    )
    _no_metrics(env)


def _sentinel_intact(env: Env) -> None:
    assert (env.dir / "precious.txt").read_text() == "keep", "the checkpoint's payload ran"
    _no_metrics(env)


def _whole_shards(env: Env) -> None:
    shards = list((env.dir / "ctrlc").rglob("*.npz"))
    assert 0 < len(shards) < 250, f"{len(shards)} of 250 shards: interrupted part way"
    for p in shards:
        with np.load(p) as z:
            list(z.keys())
    assert not list((env.dir / "ctrlc").rglob("*.tmp")), "no half-written files"


#: tests/_interrupt_hooks/sitecustomize.py: a render's processes pause before their second shard's rename
HOOKS = Path(__file__).resolve().parents[1] / "_interrupt_hooks"
REPO = Path(__file__).resolve().parents[2]


def _paused_render(env: Env) -> dict[str, str]:
    """Not a race with the render: each of its processes writes one shard, then pauses (the hook)."""
    path = os.pathsep.join([str(HOOKS), *filter(None, [os.environ.get("PYTHONPATH")])])
    return {
        "PYTHONPATH": path,
        "POSEDIFF_TEST_PAUSE_DIR": str(env.dir / "paused"),
        "POSEDIFF_TEST_PAUSE_AFTER": "1",
    }


def _render_paused(env: Env) -> bool:
    return any((env.dir / "paused").glob("paused-*"))


def _official(env: Env, shapes: tuple[str, ...] = ("tet", "cube")) -> Path:
    """A tiny unpacked symsol_dataset.zip (posediff's renders) in the case folder."""
    from posediff.data.official.fixture import make_symsol_fixture

    return make_symsol_fixture(
        env.dir / "symsol_dataset", layout="zip", n_per_shape=2, shapes=shapes, image_size=32
    )


def _official_without_image(env: Env) -> Path:
    root = _official(env)
    (root / "train" / "images" / "cube_00001.png").unlink()
    return root


def _official_truncated_png(env: Env) -> Path:
    root = _official(env)
    for png in (root / "train" / "images").glob("*.png"):
        png.write_bytes(png.read_bytes()[:60])
    return root


def _authors_symsolt(env: Env, annotations: bytes | None = None) -> Path:
    """A tiny copy of the authors' SYMSOL-T layout; ``annotations``: the test split's annotations.gz."""
    from posediff.data.official.fixture import make_symsolt_fixture

    root = make_symsolt_fixture(env.dir / "symsolt", n_per_shape=2, shapes=["tet", "cube"], image_size=32)
    if annotations is not None:
        for split in root.iterdir():
            (split / "annotations.gz").write_bytes(annotations)
    return root


class _Touch:
    """A pickled payload: unpickling it would create the sentinel file ``pwned``."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):  # noqa: ANN204
        return (os.system, (f"touch {self.target}",))


def _annotations_payload(env: Env) -> Path:
    import gzip
    import pickle

    return _authors_symsolt(env, gzip.compress(pickle.dumps([_Touch(env.dir / "pwned")])))


def _payload_did_not_run(env: Env) -> None:
    assert not (env.dir / "pwned").exists(), "the pickle's payload ran"
    _no_checkpoints(env)


def _run(env: Env) -> str:
    return f"hydra.run.dir={env.dir / 'run'}"


def _score_csv(
    env: Env,
    field: int | None = None,
    value: str | Callable[[str], str] = "",
    tail: bytes = b"",
    bom: bool = False,
) -> str:
    """A BOP19 CSV of the fixture's ground truth (one row per target instance) with field ``field`` of
    its second row (line 3) replaced by ``value`` (or by ``value(old)``), ``tail`` appended and a UTF-8
    byte-order mark in front if ``bom``; returns the ``csv=`` override."""
    import json

    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for t in json.loads((env.bop / "test_targets_bop19.json").read_text()):
        gt = json.loads((env.bop / "test_primesense" / f"{t['scene_id']:06d}" / "scene_gt.json").read_text())
        for g in gt[str(t["im_id"])]:
            if g["obj_id"] == t["obj_id"]:
                R, tt = " ".join(map(repr, g["cam_R_m2c"])), " ".join(map(repr, g["cam_t_m2c"]))
                lines.append(f"{t['scene_id']},{t['im_id']},{g['obj_id']},1.0,{R},{tt},0.5")
    if field is not None:
        row = lines[2].split(",")
        row[field] = value(row[field]) if callable(value) else value
        lines[2] = ",".join(row)
    path = env.dir / "method_bop-test.csv"
    path.write_bytes(b"\xef\xbb\xbf" * bom + ("\n".join(lines) + "\n").encode() + tail)
    return f"csv={path}"


def _existing(env: Env) -> Path:
    folder = env.dir / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    return folder


def _score(
    env: Env, field: int | None = None, value: str | Callable[[str], str] = "", **kw: Any
) -> list[str]:
    return ["score", _score_csv(env, field, value, **kw), f"data.root={env.bop}", "vsd=false", _run(env)]


def _rotation_edit(edit: Callable[[np.ndarray], np.ndarray]) -> Callable[[str], str]:
    """A CSV ``R`` field (9 numbers, row-major) → the same field of ``edit(R)``."""
    return lambda old: " ".join(
        repr(float(v)) for v in edit(np.array(old.split(), float).reshape(3, 3)).ravel()
    )


def _edited_ckpt(env: Env, name: str, edit: Callable[[dict], None]) -> Path:
    """A copy of the toy checkpoint with ``edit`` applied to its dict (config or weights)."""
    ckpt = torch.load(env.ckpt, weights_only=True)
    edit(ckpt)
    torch.save(ckpt, env.dir / name)
    return env.dir / name


def _set_levels(c: dict) -> None:
    c["posediff_config"]["module"]["diffusion"]["schedule"]["num_levels"] = 1_000_000


def _set_width(c: dict) -> None:
    c["posediff_config"]["module"]["denoiser"]["hidden_dim"] = 2_000_000


def _nan_weight(c: dict) -> None:
    key = next(k for k, v in c["state_dict"].items() if v.is_floating_point() and v.numel() > 1)
    c["state_dict"][key] = c["state_dict"][key].clone().fill_(float("nan"))


def _reshaped_weight(c: dict) -> None:
    key = next(k for k, v in c["state_dict"].items() if v.is_floating_point() and v.dim() == 2)
    c["state_dict"][key] = torch.zeros(3, 3)


def _other_run(env: Env) -> Path:
    folder = env.dir / "earlier"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "config.yaml").write_text("seed: 1\n")
    (folder / "metrics.json").write_text("{}")
    return folder


def _earlier(env: Env, name: str) -> Path:
    """A folder holding one file of an earlier run (``name``, e.g. ``poses.json``)."""
    folder = env.dir / "earlier"
    (folder / name).parent.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(b"an earlier run's file")
    return folder


def _nothing_half_written(env: Env) -> None:
    """After a write failed: no temporary file is left, and no final name holds a fragment."""
    temps = [
        p
        for p in env.dir.rglob("*")
        if p.is_file() and (p.name.endswith((".tmp", ".partial")) or ".tmp" in p.name)
    ]
    assert not temps, temps
    for p in env.dir.rglob("*.npz"):
        with np.load(p) as z:
            list(z.keys())
    for p in env.dir.rglob("*.json"):
        if p.parent.name != "earlier":
            json.loads(p.read_text())


def _sweep_failed(env: Env) -> None:
    jobs = sorted((env.dir / "sweep").glob("*/failed.json"))
    assert len(jobs) == 1 and "num_samples" in jobs[0].read_text(), jobs


def _export_with_user_file(env: Env) -> Path:
    out = env.dir / "exp"
    code = subprocess.run([*POSEDIFF, "export", f"ckpt_path={env.ckpt}", "format=torchscript", "num_steps=2",
                           f"out={out}"], capture_output=True, text=True, cwd=env.dir)  # fmt: skip
    assert code.returncode == 0, code.stderr[-2000:]
    (out / "my_notes.txt").write_text("mine")
    return out


CASES = [
    # ---- checkpoints
    Case("ckpt_payload_eval", "refused, naming the key; the payload never runs",
         lambda e: ["eval", f"ckpt_path={_tampered(e)}", _run(e)], "is not a class posediff builds",
         after=_sentinel_intact),
    Case("ckpt_payload_predict", "refused, naming the key; the payload never runs",
         lambda e: ["predict", f"ckpt_path={_tampered(e)}", "index=0", _run(e)], "is not a class posediff builds",
         after=_sentinel_intact),
    Case("ckpt_payload_fit_resume", "refused before training; the payload never runs",
         lambda e: ["fit", *TOY, f"ckpt_path={_tampered(e)}", _run(e)], "is not a class posediff builds",
         after=_sentinel_intact),
    Case("ckpt_random_bytes", "not a PyTorch checkpoint",
         lambda e: ["eval", f"ckpt_path={_write(e, 'x.ckpt', os.urandom(1000))}", _run(e)],
         "is not a PyTorch checkpoint"),
    Case("ckpt_missing_file", "not found, and where fit writes them",
         lambda e: ["eval", f"ckpt_path={e.dir / 'none.ckpt'}", _run(e)], "not found"),
    Case("eval_without_ckpt_path", "ckpt_path is required",
         lambda e: ["eval", _run(e)], "ckpt_path is required"),
    Case("resume_other_architecture", "refused before training, naming the first differing tensor",
         lambda e: ["fit", *TOY, "denoiser.hidden_dim=24", f"ckpt_path={e.ckpt}", _run(e)],
         "trained with another architecture", after=_no_metrics),
    # ---- outputs
    Case("demo_out_parent", "refused: a folder that holds the working folder",
         lambda e: ["demo", "out=.."], "holds the working folder"),
    Case("demo_out_foreign", "refused: not made by posediff, left alone",
         lambda e: (e.dir / "mine").mkdir() or (e.dir / "mine" / "f.txt").write_text("x") and
         ["demo", f"out={e.dir / 'mine'}"], "not made by posediff"),
    Case("make_bop_overwrite_parent", "refused: a folder that holds the working folder",
         lambda e: ["data", "make-bop", "out=..", "overwrite=true"], "holds the working folder"),
    Case("make_bop_overwrite_foreign", "refused: not made by posediff, left alone",
         lambda e: (e.dir / "mine").mkdir() or (e.dir / "mine" / "f.txt").write_text("x") and
         ["data", "make-bop", f"out={e.dir / 'mine'}", "overwrite=true"], "not made by posediff"),
    Case("run_dir_under_a_file", "the file in the way is named",
         lambda e: _write(e, "afile", b"x") and ["eval", f"ckpt_path={e.ckpt}", f"hydra.run.dir={e.dir / 'afile' / 'x'}"],
         "which is a file, not a folder"),
    # ---- numeric options (all before training or writing)
    Case("fit_sampler_steps_negative", "refused before training (not stored in a checkpoint)",
         lambda e: ["fit", *TOY, "sampler.num_steps=-1", _run(e)], "sampler.num_steps must be", after=_no_checkpoints),
    Case("fit_eval_steps_zero", "refused before training",
         lambda e: ["fit", *TOY, "eval.num_steps=[0]", _run(e)], "eval.num_steps must be", after=_no_checkpoints),
    Case("fit_before_samples_zero", "refused before training",
         lambda e: ["fit", *TOY, "eval.before_num_samples=0", _run(e)], "eval.before_num_samples must be",
         after=_no_checkpoints),
    Case("fit_max_steps", "refused before training",
         lambda e: ["fit", *TOY, "trainer.max_steps=-5", _run(e)], "trainer.max_steps must be", after=_no_checkpoints),
    Case("eval_max_inputs_negative", "refused (was an empty table, exit 0)",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", "max_inputs=-1", _run(e)], "max_inputs must be",
         after=_no_metrics),
    Case("eval_num_samples_zero", "refused",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", "num_samples=0", _run(e)], "num_samples must be"),
    Case("predict_index_negative", "refused",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", "index=-1", _run(e)], "index must be"),
    Case("render_negative_size", "refused; nothing written, so the corrected run works",
         lambda e: [*RENDER, "image_size=-5", f"out={e.dir / 'r'}"], "image_size",
         after=lambda e: not (e.dir / "r").exists() or pytest.fail("render wrote before failing")),
    # ---- images
    Case("predict_truncated_png", "truncated or corrupt, save it again",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={_truncated_png(e)}", _run(e)], "truncated"),
    Case("predict_decompression_bomb", "over the pixel limit, checked from the header",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={_bomb(e)}", _run(e)], "decompression-bomb guard"),
    Case("predict_not_an_image", "not an image PIL can read",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={_write(e, 'x.png', b'hello')}", _run(e)],
         "not an image"),
    Case("predict_float_image", "32-bit pixels refused",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={_png(e, 'f.tif', np.zeros((8, 8), np.float32), 'F')}",
                    _run(e)], "32-bit"),
    Case("predict_toy_checkpoint_on_image", "not trained on images",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={_png(e, 'ok.png', np.zeros((8, 8, 3), np.uint8))}",
                    _run(e)], "was not trained on images"),
    # ---- BOP data
    Case("bop_missing_train_mask", "refused up front, naming the file (was a crash mid-training)",
         lambda e: ["fit", *BOP, f"data.root={_bop_without(e, 'train_pbr/*/mask_visib/*.png')}", _run(e)],
         "is missing", after=_no_checkpoints),
    Case("bop_missing_train_rgb", "refused up front, naming the file",
         lambda e: ["fit", *BOP, f"data.root={_bop_without(e, 'train_pbr/*/rgb/*')}", _run(e)], "is missing",
         after=_no_checkpoints),
    Case("bop_missing_test_depth", "refused up front (was a failure once an estimate overlapped)",
         lambda e: ["fit", *BOP, f"data.root={_bop_without(e, 'test_primesense/*/depth/*.png')}", _run(e)],
         "is missing", after=_no_checkpoints),
    Case("bop_test_image_wrong_size", "refused up front (was accepted)",
         lambda e: ["fit", *BOP, f"data.root={_bop_resized_test_image(e)}", _run(e)], "pixels, not",
         after=_no_checkpoints),
    Case("bop_no_diameter", "refused, naming the object (was a KeyError)",
         lambda e: ["fit", *BOP, f"data.root={_bop_without_diameter(e)}", _run(e)], "diameter",
         after=_no_checkpoints),
    Case("bop_missing_root", "the path and the command that makes a dataset",
         lambda e: ["fit", *BOP, f"data.root={e.dir / 'nothere'}", _run(e)], "make-bop"),
    # ---- BOP19 results files (posediff score)
    Case("score_missing_csv", "the path and the format expected",
         lambda e: ["score", f"csv={e.dir / 'none.csv'}", f"data.root={e.bop}", _run(e)], "no such file"),
    Case("score_unknown_object", "the file and line, the objects there are",
         lambda e: _score(e, 2, "77"), "method_bop-test.csv:3: obj_id 77 is not in"),
    Case("score_image_not_a_target", "the file and line; the image holds no target",
         lambda e: _score(e, 1, "999"), "method_bop-test.csv:3: scene 1 image 999 holds no target"),
    Case("score_R_of_8_numbers", "the file and line; R needs 9 numbers",
         lambda e: _score(e, 4, "1 0 0 0 1 0 0 0"), "method_bop-test.csv:3: R has 8 numbers"),
    Case("score_non_finite", "the file and line; non-finite numbers refused",
         lambda e: _score(e, 5, "0 nan 600"), "method_bop-test.csv:3: non-finite"),
    Case("score_not_a_bop_dataset", "the path and the command that makes a dataset",
         lambda e: ["score", _score_csv(e), f"data.root={e.dir / 'nothere'}", _run(e)], "make-bop"),
    # ---- posediff export
    Case("export_unknown_format", "the formats listed",
         lambda e: ["export", f"ckpt_path={e.ckpt}", "format=tflite", f"out={e.dir / 'x'}"],
         "unknown format 'tflite'; choose one of: onnx, torchscript, exported_program"),
    Case("export_missing_checkpoint", "not found, and where fit writes them",
         lambda e: ["export", f"ckpt_path={e.dir / 'none.ckpt'}", f"out={e.dir / 'x'}"], "not found"),
    Case("export_out_exists", "refused; another folder or overwrite=true",
         lambda e: ["export", f"ckpt_path={e.ckpt}", "format=torchscript", f"out={_existing(e)}"], "already exists"),
    # ---- posediff distill
    Case("distill_steps_zero", "steps named with its range",
         lambda e: ["distill", f"ckpt_path={e.ckpt}", "steps=0", _run(e)],
         "steps must be a whole number [1, 100], got 0", after=_no_checkpoints),
    Case("distill_missing_checkpoint", "not found, and where fit writes them",
         lambda e: ["distill", f"ckpt_path={e.dir / 'none.ckpt'}", _run(e)], "not found"),
    Case("distill_unknown_method", "the methods listed",
         lambda e: ["distill", f"ckpt_path={e.ckpt}", "method=magic", _run(e)],
         "unknown method 'magic'; options: segment, reflow", after=_no_checkpoints),
    Case("distill_reflow_score_model", "refused: reflow straightens a flow model; method=segment named",
         lambda e: ["distill", f"ckpt_path={e.ckpt}", "method=reflow", _run(e)], "use method=segment",
         after=_no_checkpoints),
    # ---- flow matching (diffusion.objective)
    Case("fit_unknown_objective", "the objectives listed, before training",
         lambda e: ["fit", *TOY, "diffusion.objective=rectified", _run(e)],
         "unknown objective 'rectified'; options: dsm, flow", after=_no_checkpoints),
    Case("fit_flow_with_score_sampler", "refused before training; the flow samplers named",
         lambda e: ["fit", *TOY, "diffusion.objective=flow", _run(e)],
         "use sampler=flow_euler or sampler=flow_heun", after=_no_checkpoints),
    # ---- SYMSOL data
    Case("symsol_missing_root", "the path and the command that renders it",
         lambda e: ["fit", *SYMSOL, f"data.root={e.dir / 'nothere'}", _run(e)], "posediff data render"),
    Case("symsol_corrupt_shard", "the shard named, re-render (was a 40-90 line traceback)",
         lambda e: ["fit", *SYMSOL, f"data.root={_symsol_corrupt_shard(e)}", _run(e)], ".npz",
         after=_no_checkpoints),
    Case("symsol_meta_is_a_list", "the file named",
         lambda e: ["fit", *SYMSOL, f"data.root={_symsol_meta(e, '[]')}", _run(e)], "meta.json"),
    Case("render_resume_other_seed", "refused: the shards were rendered from another seed",
         lambda e: [*RENDER, "split=train", "seed=1", f"out={_symsol_without_meta(e)}"], "seed"),
    # ---- the benchmarks' own files (data=symsol_official, data=symsolt_official)
    Case("official_neither_layout", "the folder named, both layouts described",
         lambda e: ["fit", *OFFICIAL, f"data.root={e.dir}", _run(e)], "neither official SYMSOL layout",
         after=_no_checkpoints),
    Case("official_npz_key_missing", "rotations.npz named, the shapes it holds",
         lambda e: ["fit", *OFFICIAL, f"data.root={_official(e, ('tet',))}", _run(e)], "no rotations for cube",
         after=_no_checkpoints),
    Case("official_count_mismatch", "the images folder named, images against rotations",
         lambda e: ["fit", *OFFICIAL, f"data.root={_official_without_image(e)}", _run(e)], "1 cube images but 2 rotations",
         after=_no_checkpoints),
    Case("official_truncated_png", "the image file named",
         lambda e: ["fit", *OFFICIAL, f"data.root={_official_truncated_png(e)}", _run(e)], ".png: not a readable image",
         after=_no_checkpoints),
    Case("symsolt_annotations_not_gzip", "annotations.gz named: not gzip",
         lambda e: ["fit", *OFFICIAL_T, f"data.root={_authors_symsolt(e, b'plain text')}", _run(e)], "not a gzip file",
         after=_no_checkpoints),
    Case("symsolt_annotations_payload", "refused, the class named; the payload never runs",
         lambda e: ["fit", *OFFICIAL_T, f"data.root={_annotations_payload(e)}", _run(e)], "nothing in it was run",
         after=_payload_did_not_run),
    # ---- names
    Case("unknown_group", "the registered groups listed",
         lambda e: ["fit", "group=nope"], "available: r3so3, se2, se3, so3"),
    Case("unknown_command", "the commands listed", lambda e: ["fitt"], "available:"),
    Case("encoder_weights_missing", "the file named",
         lambda e: ["fit", *SYMSOL, "data.mode=render", "data.n_per_shape_train=2",
                    f"encoder.weights={e.dir / 'none.pt'}", _run(e)], "none.pt"),
    # ---- the command line (Hydra's own errors, paths, option values)
    Case("unknown_key", "one line: the closest keys and how to add a new one",
         lambda e: ["fit", *TOY, "trainer.max_step=3", _run(e)], "unknown key trainer.max_step: did you mean trainer.max_steps"),
    Case("experiment_twice", "one line: give one experiment",
         lambda e: ["fit", "+experiment=toy_so3", "+experiment=toy_se3", _run(e)], "experiment is given more than once"),
    Case("path_with_quote", "the path is read as written (quoted for Hydra)",
         lambda e: ["eval", f"ckpt_path={e.dir}/it's.ckpt", _run(e)], "it's.ckpt not found"),
    Case("path_with_equals_comma_bracket", "the path is read as written (quoted for Hydra)",
         lambda e: ["eval", f"ckpt_path={e.dir}/a=b,[1].ckpt", _run(e)], "a=b,[1].ckpt not found"),
    Case("path_unicode", "the path is read as written (quoted for Hydra)",
         lambda e: ["eval", f"ckpt_path={e.dir}/données.ckpt", _run(e)], "données.ckpt not found"),
    Case("path_tilde", "~ is expanded",
         lambda e: ["eval", "ckpt_path=~/posediff-no-such.ckpt", _run(e)], f"{Path.home()}/posediff-no-such.ckpt not found"),
    Case("option_text_num_samples", "the key named with its bounds",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", "num_samples=abc", _run(e)], "num_samples must be a whole number"),
    Case("option_text_sampler_steps", "the key named with its bounds",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", "sampler.num_steps=abc", _run(e)], "sampler.num_steps must be a whole number"),
    Case("fit_lr_negative", "refused before training (was a 40-line optimizer traceback)",
         lambda e: ["fit", *TOY, "module.lr=-1", _run(e)], "module.lr must be", after=_no_checkpoints),
    Case("fit_lr_nan", "refused before training",
         lambda e: ["fit", *TOY, "module.lr=nan", _run(e)], "module.lr must be", after=_no_checkpoints),
    Case("fit_num_noisy_zero", "refused before training",
         lambda e: ["fit", *TOY, "module.num_noisy=0", _run(e)], "module.num_noisy must be", after=_no_checkpoints),
    Case("fit_seed_negative", "refused before training",
         lambda e: ["fit", *TOY, "seed=-1", _run(e)], "seed must be", after=_no_checkpoints),
    Case("fit_image_size_huge", "refused before anything is built (was PIL out of memory)",
         lambda e: ["fit", *SYMSOL, f"data.root={e.symsol}", "data.image_size=60000", _run(e)],
         "data.image_size must be", after=_no_checkpoints),
    Case("predict_min_mode_weight", "refused before sampling",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", "index=0", "min_mode_weight=2", _run(e)], "min_mode_weight must be"),
    Case("predict_mode_radius_inf", "refused before sampling",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", "index=0", "mode_radius_deg=inf", _run(e)], "mode_radius_deg must be"),
    # ---- sizes and weights read from a file
    Case("ckpt_million_levels", "refused before anything is built (was a 90 s walk)",
         lambda e: ["predict", f"ckpt_path={_edited_ckpt(e, 'l.ckpt', _set_levels)}", "index=0", _run(e)],
         "num_levels = 1000000 is out of bounds"),
    Case("ckpt_huge_layer", "refused before allocating (was 12-32 GB)",
         lambda e: ["eval", f"ckpt_path={_edited_ckpt(e, 'w.ckpt', _set_width)}", _run(e)],
         "hidden_dim = 2000000 is out of bounds"),
    Case("ckpt_nan_weights_eval", "refused, naming the weight (was exit 0 with NaN metrics)",
         lambda e: ["eval", f"ckpt_path={_edited_ckpt(e, 'n.ckpt', _nan_weight)}", _run(e)],
         "NaN/infinite", after=_no_metrics),
    Case("ckpt_nan_weights_predict", "refused, naming the weight (was a NaN poses.json, or a segfault)",
         lambda e: ["predict", f"ckpt_path={_edited_ckpt(e, 'n.ckpt', _nan_weight)}", "index=0", _run(e)],
         "NaN/infinite"),
    Case("ckpt_tensor_other_shape", "refused, naming the tensor (was a traceback)",
         lambda e: ["predict", f"ckpt_path={_edited_ckpt(e, 's.ckpt', _reshaped_weight)}", "index=0", _run(e)],
         "do not fit the architecture"),
    # ---- runs never mix; sweeps say when a job failed
    Case("run_dir_of_another_run", "refused: that folder holds another run's files",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", f"hydra.run.dir={_other_run(e)}"], "holds another run's files"),
    Case("predict_over_a_prediction", "refused: the folder holds an earlier prediction (was overwritten)",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", "index=0", f"hydra.run.dir={_earlier(e, 'poses.json')}"],
         "holds another run's files"),
    Case("fit_into_another_run", "refused: the folder holds another run's checkpoint (was mixed with it)",
         lambda e: ["fit", *TOY, f"hydra.run.dir={_earlier(e, 'checkpoints/last.ckpt')}"], "holds another run's files"),
    Case("sweep_job_fails", "exit 2: the failed job's line, then how many failed (failed.json in its folder)",
         lambda e: ["eval", f"ckpt_path={e.ckpt}", "-m", "num_samples=1,0", f"hydra.sweep.dir={e.dir / 'sweep'}"],
         "1 of 2 jobs failed", lines=2, after=_sweep_failed),
    Case("export_overwrite_user_file", "refused: a file posediff did not write is never deleted",
         lambda e: ["export", f"ckpt_path={e.ckpt}", "format=torchscript", "num_steps=2",
                    f"out={_export_with_user_file(e)}", "overwrite=true"], "not written by posediff"),
    # ---- results files: rotations are checked, encodings named
    Case("score_R_scaled", "the file and line: R is a rotation scaled by 2 (was scored as right)",
         lambda e: _score(e, 4, _rotation_edit(lambda R: 2 * R)), "method_bop-test.csv:3: R looks like a rotation scaled by 2"),
    Case("score_R_reflection", "the file and line: R has det -1, a reflection (was scored)",
         lambda e: _score(e, 4, _rotation_edit(lambda R: -R)), "method_bop-test.csv:3: R has det -1"),
    Case("score_R_zeros", "the file and line: R is all zeros (was scored)",
         lambda e: _score(e, 4, "0 0 0 0 0 0 0 0 0"), "method_bop-test.csv:3: R is all zeros"),
    Case("score_latin1", "the file, line and byte: not UTF-8 (was no file, no line)",
         lambda e: _score(e, tail="# m\xe9thode\n".encode("latin-1")), "not UTF-8 text (byte 0xe9"),
    Case("score_byte_order_mark", "read as written, scored (was blamed on \"could not convert 'R'\")",
         lambda e: _score(e, bom=True), "AR", code=0, lines=0),
    # ---- image paths that are not image files
    Case("predict_image_folder", "a folder, not an image file (was \"not found\")",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", f"image={e.dir}", _run(e)], "is a folder, not an image file"),
    Case("predict_image_device", "not a regular file (was \"not found\")",
         lambda e: ["predict", f"ckpt_path={e.ckpt}", "image=/dev/null", _run(e)], "is not a regular file"),
    # ---- export sizes
    Case("export_onnx_many_steps", "refused at once, with the bound (was still unrolling after 14 min)",
         lambda e: ["export", f"ckpt_path={e.ckpt}", "format=onnx", "num_steps=50", f"out={e.dir / 'x'}"],
         "above max_unrolled=20", after=lambda e: not (e.dir / "x").exists() or pytest.fail("export wrote")),
    # ---- full disks and closed outputs
    Case("render_disk_full", "one line naming the file; no half-written shard (was a traceback)",
         lambda e: [*RENDER, "split=test", f"out={e.dir / 'r'}"], "file too large for the file system writing",
         file_limit=1500,  # meta.json and index.npz fit, a shard does not
         after=_nothing_half_written),
    Case("predict_disk_full", "one line naming the file; nothing half-written (was a traceback)",
         lambda e: ["predict", f"ckpt_path={e.image_ckpt}", "index=0", "num_samples=50", _run(e)],
         "file too large for the file system writing", file_limit=5000,  # .hydra fits, poses.npz does not
         after=_nothing_half_written),
    Case("eval_disk_full", "one line naming the file; nothing half-written (was a traceback)",
         lambda e: ["eval", f"ckpt_path={e.image_ckpt}", "num_samples=2", "hydra.output_subdir=null", _run(e)],
         "file too large for the file system writing", file_limit=1000,  # metrics.md fits, metrics.json not
         after=_nothing_half_written),
    Case("stdout_closed", "quiet, exit 141, as Unix tools under `| head -1` (was a traceback)",
         lambda e: ["check", "group=so3"], "", code=141, lines=0, stdout="closed"),
    Case("stdout_full", "one line: cannot write to standard output (was a traceback)",
         lambda e: ["check", "group=so3"], "cannot write to standard output", stdout="full"),
    Case("render_osmesa", "one line: how to render offscreen here (was a 65-line traceback; the BOP renderer is the one on GL)",
         lambda e: ["data", "make-bop", f"out={e.dir / 'osmesa_bop'}"], "PYOPENGL_PLATFORM=osmesa",
         environ=lambda e: {"PYOPENGL_PLATFORM": "osmesa"}),
    # ---- Ctrl-C
    Case("fit_ctrl_c", "exit 130, one line: the step reached and how to resume",
         lambda e: ["fit", *[a for a in TOY if not a.startswith("trainer.max_steps")], "trainer.max_steps=100000",
                    "trainer.log_every_n_steps=1", _run(e)], "fit stopped at step", code=130,
         interrupt=lambda e: "step" in _text(e.dir / "run" / "progress.log")),
    Case("render_ctrl_c", "exit 130, one line; every shard on disk is whole",
         lambda e: [*RENDER[:-4], "n_per_shape=400", "shard_size=8", "progress=false", f"out={e.dir / 'ctrlc'}"],
         "interrupted", code=130, interrupt=_render_paused, after=_whole_shards, environ=_paused_render),
]  # fmt: skip


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


#: runs the CLI with its largest file size limited to argv[1] bytes (RLIMIT_FSIZE): the disk is "full"
#: once a file would pass it (Python ignores SIGXFSZ, so the write fails with EFBIG)
LIMITED = [sys.executable, "-c", "import resource, sys; from posediff.cli import main; "
           "resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY)); "
           "sys.exit(main(sys.argv[2:]))"]  # fmt: skip

#: what the fork server imports once, so that a case's process starts with torch, Lightning, Hydra and
#: posediff loaded (a new interpreter spends ~5 s importing them, 90 times over)
PRELOAD = ["torch", "lightning.pytorch", "hydra", "posediff.cli", "posediff.cli.commands.fit", "posediff.cli.commands.eval", "posediff.evaluation",
           "posediff.models.export", "posediff.data.symsol", "posediff.data.bop", __name__]  # fmt: skip


def _fresh_interpreter(case: Case) -> bool:
    """Cases that need a new interpreter: a start-up environment (PYTHONPATH hooks, the GL platform), a
    stdout that is not a pipe (the interpreter's own last flush), or a Ctrl-C (Python's default SIGINT
    handler, in a process group of its own)."""
    return case.environ is not None or case.stdout != "pipe" or case.interrupt is not None


def _cli_in_fork(args: list[str], cwd: str, file_limit: int | None, out_path: str, err_path: str) -> None:
    """``posediff <args>`` in a process forked from the fork server: ``posediff.cli.main`` exactly as
    the console script runs it, with stdout and stderr to files and the exit code its exit status."""
    import resource
    import traceback
    import warnings

    os.chdir(cwd)
    for fd, path in ((1, out_path), (2, err_path)):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(f, fd)
        os.close(f)
    os.environ.update({"PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"})
    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    if file_limit is not None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (file_limit, resource.RLIM_INFINITY))
    sys.argv = ["posediff", *args]
    try:
        code = main(args)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    except BaseException:
        traceback.print_exc()
        code = 1
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        # the exit code also goes to a file: the fork server reports a child's status over a pipe of its
        # own, and where that pipe fails (seen once in CI) multiprocessing says 255 whatever the exit was
        Path(out_path).with_suffix(".code").write_text(str(code))
    finally:
        os._exit(code)


def _execute(case: Case, env: Env) -> tuple[int, str, str, dict[str, bytes]]:
    args = case.args(env)
    (env.dir / "precious.txt").exists() or (env.dir / "precious.txt").write_text("keep")
    before = _snapshot(env.dir)
    cwd = env.dir / "work"
    cwd.mkdir(exist_ok=True)
    (cwd / "notes.txt").write_text("my notes")
    before = {**before, "work/notes.txt": b"my notes"}
    if not _fresh_interpreter(case):
        return (*_execute_forked(case, args, cwd), before)
    command = [*POSEDIFF, *args] if case.file_limit is None else [*LIMITED, str(case.file_limit), *args]
    stdout: Any = subprocess.PIPE
    if case.stdout == "closed":  # the reading end closed before anything is written: `| head -0`
        read_end, stdout = os.pipe()
        os.close(read_end)
    elif case.stdout == "full":
        stdout = open("/dev/full", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        command,
        cwd=cwd,
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
        env={
            **os.environ,
            "PYTHONWARNINGS": "ignore",
            "OMP_NUM_THREADS": "1",
            **(case.environ(env) if case.environ else {}),
        },
    )
    if case.stdout == "closed":
        os.close(stdout)
    elif case.stdout == "full":
        stdout.close()
    if case.interrupt is not None:  # Ctrl-C once the case is where it should be interrupted
        deadline = time.monotonic() + 400  # (under load, starting torch and the renderer can take minutes)
        while not case.interrupt(env) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out or "", err, before


def _execute_forked(case: Case, args: list[str], cwd: Path) -> tuple[int, str, str]:
    import multiprocessing

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    out_path, err_path = cwd.parent / f".{case.id}.stdout", cwd.parent / f".{case.id}.stderr"
    proc = ctx.Process(
        target=_cli_in_fork, args=(args, str(cwd), case.file_limit, str(out_path), str(err_path))
    )
    proc.start()
    proc.join(timeout=300)
    if proc.is_alive():
        proc.kill()
        proc.join()
    out, err = out_path.read_text(errors="replace"), err_path.read_text(errors="replace")
    out_path.unlink()
    err_path.unlink()
    code = proc.exitcode if proc.exitcode is not None else -9
    code_path = out_path.with_suffix(".code")
    if code_path.exists():  # the code main() returned, written just before os._exit(code)
        written = int(code_path.read_text())
        code_path.unlink()
        if code in (written, 255):  # 255: the fork server's status pipe failed (popen_forkserver.poll)
            code = written
    return code, out, err


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Env:
    from posediff.data.bop.fixture import make_bop_fixture

    base = tmp_path_factory.mktemp("bad_inputs")
    run = base / "toy"
    assert main(["fit", *TOY, f"hydra.run.dir={run}"]) == 0
    bop = base / "bop"
    make_bop_fixture(bop, seed=0, width=96, height=72, pbr_scenes=1, pbr_images=2, train_views=2,
                     test_scenes=1, test_images=1)  # fmt: skip
    symsol = base / "symsol"
    for split in ("train", "test"):
        assert main([*RENDER, f"split={split}", f"out={symsol}"]) == 0
    image = base / "image"
    assert main(["fit", *SYMSOL, f"data.root={symsol}", f"hydra.run.dir={image}"]) == 0
    return Env(ckpt=run / "checkpoints" / "last.ckpt", bop=bop, symsol=symsol,
               image_ckpt=image / "checkpoints" / "last.ckpt")  # fmt: skip


@pytest.fixture(scope="module")
def results(env: Env, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple]:
    shared_before = {name: _snapshot(p) for name, p in (("bop", env.bop), ("symsol", env.symsol))}
    base = tmp_path_factory.mktemp("cases")

    def one(case: Case) -> tuple:
        case_env = copy.copy(env)
        case_env.dir = base / case.id
        case_env.dir.mkdir()
        return (*_execute(case, case_env), case_env)

    with ThreadPoolExecutor(max_workers=2) as pool:
        done = dict(zip([c.id for c in CASES], pool.map(one, CASES), strict=True))
    for name, p in (("bop", env.bop), ("symsol", env.symsol)):
        assert _snapshot(p) == shared_before[name], f"the shared {name} input changed"
    return done


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_gets_one_line(case: Case, results: dict[str, tuple]) -> None:
    code, out, err, before, case_env = results[case.id]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err + out, err[-3000:]
    assert code == case.code, (code, err[-2000:])
    assert len(lines) == case.lines and all(ln.startswith("posediff") for ln in lines), lines[-20:]
    assert case.message in (lines[-1] if lines else out), (lines or out)[-20:]
    after = _snapshot(case_env.dir)
    damaged = [k for k, v in before.items() if after.get(k) != v]
    assert not damaged, f"files changed or removed: {damaged}"
    if case.after is not None:
        case.after(case_env)


def test_table_is_in_the_docs() -> None:
    """docs/reliability.md counts these cases and lists each with what it gets."""
    page = (REPO / "docs" / "reliability.md").read_text()
    assert f"{len(CASES)} bad inputs" in page
    missing = [c.id for c in CASES if f"| `{c.id}` | {c.gets} | {c.code} |" not in page]
    assert not missing, f"docs/reliability.md's table lacks {missing}"


def test_sixteen_bit_grey_png_is_read_not_whitened(tmp_path: Path) -> None:
    """A 16-bit grey PNG was 99.7 % white after PIL's RGB conversion; it is scaled by 65535 now."""
    from posediff.evaluation.predict import load_image

    grey = np.linspace(0, 65535, 32 * 32).reshape(32, 32).astype(np.uint16)
    path = _png(Env(Path(), Path(), Path(), Path(), dir=tmp_path), "g16.png", grey)
    from PIL import Image

    assert Image.open(path).mode.startswith("I;16")
    img = load_image(path, 32)
    assert img.shape == (3, 32, 32)
    np.testing.assert_allclose(img.mean().item(), 0.5, atol=0.01)
    np.testing.assert_allclose(img[0].numpy(), grey / 65535.0, atol=1 / 255 + 1e-6)
