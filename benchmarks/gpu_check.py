"""The one GPU check: what a short loan of a GPU should measure, in one command (`make gpu-check`).

    python benchmarks/gpu_check.py                         # on a GPU: the full check, ≤ --budget-s (480 s)
    python benchmarks/gpu_check.py --tiny --out /tmp/g.json   # anywhere: every section at toy sizes (the tests run it)

Sections (each timed, each failure recorded with its one-line reason and the check goes on):

1. **environment** — GPU name, driver, torch / CUDA versions, the EGL vendor the renderer gets.
2. **render** — SYMSOL-T at 224 px through EGL (NVIDIA's on a GPU machine; the vendor string says
   whether Mesa's CPU fallback was used), images/s.
3. **train** — training throughput at the paper's settings (``symsolt_se3``: ResNet34, 224 px,
   16 images × 256 noisy poses, bf16 autocast on CUDA) on synthetic batches: steps/s, images/s, peak
   memory; eager, ``channels_last`` and ``torch.compile``.
4. **sample** — the paper's Table-4 layout: steps 5 / 10 / 50 / 100 × hypotheses per image 1 / 64 /
   256, images/s and s/image, fp32 and bf16, eager vs ``torch.compile`` of the denoiser step vs CUDA
   graphs (``mode="reduce-overhead"``); batches of 16 images, the encoder once per image.
5. **learn** — the CPU recipe (``+experiment=quickstart``, rendered on the fly) trained for the time
   left, then evaluated: spread per shape, so that any GPU run yields a point of a learning curve.

Writes ``--out`` (JSON, after every section) and the same path with ``.md`` (a table per section).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

import torch  # noqa: E402

from posediff._io import atomic_write_json, atomic_write_text  # noqa: E402

FULL = {
    "render_size": 224, "render_images": 200,
    "train_arch": "resnet34", "train_size": 224, "train_batch": 16, "train_noisy": 256, "train_steps": 20,
    "sample_steps": (5, 10, 50, 100), "sample_hyps": (1, 64, 256), "sample_batch": 16,
    "sample_arch": "resnet34", "sample_size": 224, "sample_dtypes": ("fp32", "bf16"),
    "sample_modes": ("eager", "compiled", "cudagraphs"), "train_variants": ("eager", "channels_last", "compile"),
}  # fmt: skip
TINY = {
    "render_size": 32, "render_images": 5,
    "train_arch": "resnet18", "train_size": 32, "train_batch": 2, "train_noisy": 4, "train_steps": 2,
    "sample_steps": (2,), "sample_hyps": (4,), "sample_batch": 2,
    "sample_arch": "resnet18", "sample_size": 32, "sample_dtypes": ("fp32",),
    "sample_modes": ("eager", "compiled"), "train_variants": ("eager", "channels_last"),  # CPU compile of a
}  # fmt: skip  # training step takes minutes; the sampling section compiles


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def environment() -> dict[str, Any]:
    out: dict[str, Any] = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "cpus": os.cpu_count(),
    }
    if torch.cuda.is_available():
        out["gpu"] = torch.cuda.get_device_name(0)
        out["capability"] = list(torch.cuda.get_device_capability(0))
        try:
            smi = subprocess.run(["nvidia-smi", "--query-gpu=driver_version,memory.total", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=20)  # fmt: skip
            out["driver"] = smi.stdout.strip()
        except Exception as e:  # noqa: BLE001
            out["driver"] = f"unknown ({type(e).__name__})"
    return out


def render(cfg: dict[str, Any]) -> dict[str, Any]:
    """SYMSOL-T rendering speed. Since scene 2 the renderer ray casts in NumPy on the CPU (no GL), so
    this is the host's CPU speed, not the GPU's."""
    from posediff.data.symsol import SymsolRenderer, sample_poses

    n = int(cfg["render_images"])
    poses = sample_poses("symsolt", "uniform", "train", max(1, n // 5), seed=0)
    r = SymsolRenderer(int(cfg["render_size"]))
    r.render(0, poses.R[0], poses.t[0])  # the planes and ray grids
    t0 = time.perf_counter()
    for i in range(len(poses)):
        r.render(int(poses.shape_id[i]), poses.R[i], poses.t[i])
    seconds = time.perf_counter() - t0
    return {"image_size": int(cfg["render_size"]), "images": len(poses), "images_per_s": len(poses) / seconds,
            "renderer": "NumPy ray casting on the CPU (scene 2; no GL)"}  # fmt: skip


def _module(arch: str, size: int, noisy: int, group: str = "se3") -> Any:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from posediff.cli import config_dir
    from posediff.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=symsolt_se3", f"encoder.arch={arch}", f"data.image_size={size}",
                                        f"module.num_noisy={noisy}", f"group={group}"])  # fmt: skip
    return instantiate(cfg.module)


def _device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def train(cfg: dict[str, Any]) -> dict[str, Any]:
    dev = _device()
    B, S = int(cfg["train_batch"]), int(cfg["train_size"])
    rows = []
    for variant in cfg["train_variants"]:
        torch.manual_seed(0)
        module = _module(cfg["train_arch"], S, int(cfg["train_noisy"])).to(dev).train()
        if variant == "channels_last":
            module.encoder.to(memory_format=torch.channels_last)
        opt = torch.optim.Adam(module.parameters(), 1e-4)
        image = torch.rand(B, 3, S, S, device=dev)
        if variant == "channels_last":
            image = image.to(memory_format=torch.channels_last)
        pose = module.group.sample_uniform((B,), device=dev)

        def loss_fn(image: torch.Tensor, pose: torch.Tensor, module: Any = module) -> torch.Tensor:
            enc = module.encode_full(image, pose=pose)
            noisy = module.diffusion.perturb(pose, num_noisy=module.num_noisy)
            out = module(noisy.x_noisy, noisy.sigma, module.pack(enc))
            return module.diffusion.loss(out, noisy)

        step_fn = torch.compile(loss_fn) if variant == "compile" else loss_fn
        amp = (
            torch.autocast("cuda", dtype=torch.bfloat16)
            if dev.type == "cuda"
            else torch.autocast("cpu", enabled=False)
        )
        if dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        times = []
        for k in range(int(cfg["train_steps"]) + 1):
            t0 = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            with amp:
                loss = step_fn(image, pose)
            loss.backward()
            opt.step()
            _sync()
            if k:  # the first step warms up (and compiles)
                times.append(time.perf_counter() - t0)
        sec = sum(times) / len(times)
        rows.append({"variant": variant, "steps_per_s": 1.0 / sec, "images_per_s": B / sec,
                     "poses_per_s": B * int(cfg["train_noisy"]) / sec, "loss": float(loss.detach()),
                     "peak_memory_gib": torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else None})  # fmt: skip
    return {"arch": cfg["train_arch"], "image_size": S, "batch": B, "noisy": int(cfg["train_noisy"]),
            "precision": "bf16 autocast" if dev.type == "cuda" else "fp32", "rows": rows}  # fmt: skip


def sample(cfg: dict[str, Any]) -> dict[str, Any]:
    from posediff.evaluation.sampling import accelerated_denoise_fn

    dev = _device()
    torch.manual_seed(0)
    module = _module(cfg["sample_arch"], int(cfg["sample_size"]), 8).to(dev).eval()
    B = int(cfg["sample_batch"])
    image = torch.rand(B, 3, int(cfg["sample_size"]), int(cfg["sample_size"]), device=dev)
    rows = []
    modes = [m for m in cfg["sample_modes"] if m != "cudagraphs" or dev.type == "cuda"]
    for dtype_name in cfg["sample_dtypes"]:
        if dtype_name == "bf16" and dev.type != "cuda":
            continue
        for mode in modes:
            fn = accelerated_denoise_fn(module, mode)
            for steps in cfg["sample_steps"]:
                for hyps in cfg["sample_hyps"]:
                    amp = torch.autocast(dev.type, dtype=torch.bfloat16, enabled=dtype_name == "bf16")

                    def run(
                        fn: Any = fn, steps: int = steps, hyps: int = hyps, amp: Any = amp
                    ) -> torch.Tensor:
                        with torch.no_grad(), amp:
                            cond = module.encode(image)
                            return module.sampler.sample(fn, cond, hyps, steps, batch_size=B, dtype=torch.float32,
                                                         device=dev)  # fmt: skip

                    run()  # warm-up (compilation, graph capture)
                    _sync()
                    t0 = time.perf_counter()
                    reps = 0
                    while reps < 3 or (time.perf_counter() - t0 < 0.5 and reps < 20):
                        run()
                        reps += 1
                    _sync()
                    sec = (time.perf_counter() - t0) / reps / B
                    rows.append({"dtype": dtype_name, "mode": mode, "steps": steps, "hypotheses": hyps,
                                 "images_per_s": 1.0 / sec, "s_per_image": sec})  # fmt: skip
    return {"arch": cfg["sample_arch"], "image_size": int(cfg["sample_size"]), "batch": B,
            "sampler": module.sampler.name, "rows": rows}  # fmt: skip


def _dhms(seconds: float) -> str:
    s = max(1, int(seconds))
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def learn(seconds: float, tiny: bool, workdir: Path) -> dict[str, Any]:
    from posediff.cli import main

    run = workdir / "learn"
    args = ["fit", "+experiment=quickstart", "data.mode=render", "trainer.enable_progress_bar=false",
            f"hydra.run.dir={run}", f'+trainer.max_time="{_dhms(seconds)}"']  # fmt: skip
    if tiny:
        args += ["data.image_size=32", "data.n_per_shape_train=4", "data.n_per_shape_test=1", "data.batch_size=2",
                 "encoder.crop_size=16", "module.num_noisy=4", "denoiser.hidden_dim=16", "trainer.max_steps=2",
                 "trainer.val_check_interval=2", "eval.num_samples=2", "eval.num_steps=[2]", "eval.before=false"]  # fmt: skip
    else:
        args += ["data.n_per_shape_train=20000", "data.num_workers=8", "trainer.max_steps=-1",
                 "trainer.precision=bf16-mixed", "trainer.val_check_interval=500"]  # fmt: skip
    code = main(args)
    if code:
        raise RuntimeError(f"posediff fit exited {code}")
    metrics = json.loads((run / "metrics.json").read_text())
    after = next(iter(next(iter(metrics["after"].values())).values()))
    return {"seconds": seconds, "steps": metrics["train"]["steps"],
            "spread_deg": {k: v.get("spread_deg") for k, v in after["shapes"].items()},
            "overall_spread_deg": after["overall"].get("spread_deg")}  # fmt: skip


def _markdown(result: dict[str, Any]) -> str:
    lines = [f"# posediff GPU check ({'tiny' if result['tiny'] else 'full'})", "", f"{result['date']}, "
             f"{result['environment'].get('gpu', 'no GPU')}, torch {result['environment']['torch']}", ""]  # fmt: skip
    for name, sec in result["sections"].items():
        lines.append(f"## {name} ({sec.get('seconds', 0):.1f} s)")
        if "error" in sec:
            lines += ["", f"failed: {sec['error']}", ""]
            continue
        rows = sec.get("rows")
        if rows:
            keys = list(rows[0])
            lines += ["", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
            for r in rows:
                lines.append(
                    "| "
                    + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values())
                    + " |"
                )
        lines += ["", "```", json.dumps({k: v for k, v in sec.items() if k != "rows"}, indent=1), "```", ""]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tiny", action="store_true", help="every section at toy sizes (CPU, the tests)")
    ap.add_argument("--budget-s", type=float, default=480.0, help="wall-clock budget of the whole check")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/gpu_check_<gpu>.json)")
    ap.add_argument("--workdir", default=str(ROOT / "outputs" / "gpu_check"))
    args = ap.parse_args(argv)
    start = time.perf_counter()
    env = environment()
    gpu = env.get("gpu", "cpu").lower().replace(" ", "_")
    out = Path(args.out or ROOT / "benchmarks" / "results" / f"gpu_check_{gpu}.json")
    cfg = TINY if args.tiny else FULL
    result: dict[str, Any] = {"benchmark": "gpu_check", "tiny": args.tiny, "command": " ".join(sys.argv),
                              "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                              "environment": env, "sections": {}}  # fmt: skip
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    sections = [
        ("render", lambda: render(cfg)),
        ("train", lambda: train(cfg)),
        ("sample", lambda: sample(cfg)),
    ]
    for name, fn in sections:
        t0 = time.perf_counter()
        try:
            sec = fn()
        except Exception as e:  # noqa: BLE001 - a failed section is a result, the check goes on
            sec = {"error": f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}",
                   "traceback": traceback.format_exc(limit=3)}  # fmt: skip
        sec["seconds"] = time.perf_counter() - t0
        result["sections"][name] = sec
        atomic_write_json(out, result)
        print(
            f"{name}: {sec['seconds']:.1f} s" + (f" — {sec['error']}" if "error" in sec else ""), flush=True
        )
    left = args.budget_s - (time.perf_counter() - start) - 90.0  # evaluation and writing
    t0 = time.perf_counter()
    try:
        result["sections"]["learn"] = learn(left if not args.tiny else 5.0, args.tiny, workdir)
    except Exception as e:  # noqa: BLE001
        result["sections"]["learn"] = {"error": f"{type(e).__name__}: {str(e).strip()[:200]}"}
    result["sections"]["learn"]["seconds"] = time.perf_counter() - t0
    result["seconds"] = time.perf_counter() - start
    atomic_write_json(out, result)
    atomic_write_text(out.with_suffix(".md"), _markdown(result))
    print(f"wrote {out} and {out.with_suffix('.md')} ({result['seconds']:.0f} s)")
    return 0 if not any("error" in s for s in result["sections"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
