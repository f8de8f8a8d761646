"""One training step at the hardware's pace: where a ``quickstart`` step spends its time, and what each
speed lever gives, measured in one run.

Two parts, each variant in a fresh subprocess (its own peak memory, no compile cache shared):

* **profile** — a training step split by ``torch.profiler`` into data (the next batch from the
  DataLoader), encoder forward, perturbation, denoiser forward, losses (the named ranges of
  ``PoseDiffusionModule.training_step``), backward and the optimizer; plus the forward group math
  (the self time of every op called from ``posediff/lie/``), steps/s and peak memory (max RSS).
* **levers** — steps/s of the real ``lightning.Trainer.fit`` (the ``posediff fit`` path, without
  loggers and checkpoints) for today's settings and with each lever on: ``module.optimizer_impl``
  (foreach / fused Adam), ``module.channels_last``, ``module.compile`` (inductor on the CPU),
  ``trainer.precision=bf16-mixed`` (only where the CPU has native bf16), thread settings, DataLoader
  workers; and all winners together. The first ``--warmup`` steps (compilation included) are not timed.

    python benchmarks/train_step.py                        # quickstart and symsolt_se3 at batch 16
    python benchmarks/train_step.py --only quickstart --steps 40
    make bench-train

Results: ``benchmarks/results/train_step.json`` (rewritten after every variant) and
``benchmarks/results/train_step.md``. Data: a small SYMSOL-T render at 128 px under
``benchmarks/.work/`` (made on first use; ~15 s).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
WORK = ROOT / "benchmarks" / ".work" / "train_step"
DATA = WORK / "symsolt128"

#: the experiments timed: name → overrides of ``posediff fit`` (symsolt_se3, the paper's ResNet34 model,
#: CPU-sized: 128 px images, batch 16, fp32, the main process loading — its GPU settings are bf16 and 4 workers)
EXPERIMENTS: dict[str, list[str]] = {
    "quickstart": ["+experiment=quickstart"],
    "symsolt_se3": [
        "+experiment=symsolt_se3",
        "data.batch_size=16",
        "data.image_size=128",
        "data.num_workers=0",
        "trainer.precision=32-true",
    ],  # fmt: skip
}

#: the code path before the levers (each lever is measured on top of it; "defaults" is today's config)
TODAY = ["module.optimizer_impl=default", "module.channels_last=false", "module.compile=false"]

#: the levers: name → (what it is, overrides on top of the experiment's and TODAY)
LEVERS: dict[str, tuple[str, list[str]]] = {
    "today": ("the settings before this benchmark (for-loop Adam, contiguous, eager, fp32)", TODAY),
    "foreach_adam": ("Adam's multi-tensor (foreach) update", ["module.optimizer_impl=foreach"]),
    "fused_adam": ("Adam's fused CPU kernel", ["module.optimizer_impl=fused"]),
    "channels_last": (
        "the ResNet's weights and activations in channels-last order",
        ["module.channels_last=true"],
    ),
    "compile": ("torch.compile (inductor) of the encoder and the denoiser", ["module.compile=true"]),
    "fused_channels_last": (
        "fused Adam and channels-last together",
        ["module.optimizer_impl=fused", "module.channels_last=true"],
    ),
    "bf16": (
        "bf16 autocast (Lightning's bf16-mixed); only where the CPU has native bf16",
        ["trainer.precision=bf16-mixed"],
    ),
    "workers_1": ("one DataLoader worker process instead of the main process", ["data.num_workers=1"]),
    "threads_1_interop": ("one inter-op thread (intra-op threads unchanged)", ["+bench.interop_threads=1"]),
}


#: the code paths ``--curve`` compares: name → overrides on top of the experiment's
CURVE_PATHS: dict[str, list[str]] = {
    "today": TODAY,
    "defaults": [],
    "defaults_bf16": LEVERS["bf16"][1],
}


# --------------------------------------------------------------------------------------------------
# building the run (the composition root's configs, instantiated as posediff fit does)
# --------------------------------------------------------------------------------------------------


def ensure_data() -> Path:
    """A SYMSOL-T render at 128 px, train (40 per shape) and test (4 per shape), made once."""
    for split, n in (("train", 40), ("test", 4)):
        if not (DATA / split / "meta.json").exists():
            cmd = [sys.executable, "-m", "posediff.cli", "data", "render", "dataset=symsolt", f"split={split}",
                   "image_size=128", f"n_per_shape={n}", "progress=false", f"out={DATA}"]  # fmt: skip
            subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return DATA


def compose(overrides: list[str]) -> Any:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from posediff.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return hydra_compose("fit", overrides=overrides)


def build(overrides: list[str]) -> tuple[Any, Any, Any]:
    """``(cfg, datamodule, module)`` of ``posediff fit <overrides>``."""
    from hydra.utils import instantiate

    cfg = compose([*overrides, f"data.root={DATA}", "data.n_per_shape_test=4"])
    bench = cfg.get("bench") or {}
    import torch

    if bench.get("interop_threads"):
        torch.set_num_interop_threads(int(bench["interop_threads"]))
    if bench.get("threads"):
        torch.set_num_threads(int(bench["threads"]))
    import lightning as L

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    module = instantiate(cfg.module)
    return cfg, datamodule, module


def peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------------------------------
# the worker: one variant, in its own process
# --------------------------------------------------------------------------------------------------


def fit_speed(overrides: list[str], steps: int, warmup: int) -> dict[str, Any]:
    """Steps/s of ``lightning.Trainer.fit`` over ``steps`` steps after ``warmup`` (not timed)."""
    import lightning as L
    import torch

    cfg, datamodule, module = build(overrides)
    if "bf16" in str(cfg.trainer.precision) and not bf16_native():
        return {"skipped": "this CPU has no native bf16 (AVX512-BF16 / AMX): autocast would emulate it"}
    times: list[float] = []
    cpu: list[
        float
    ] = []  # the process's CPU time (all threads): less sensitive than wall time to a busy host
    losses: list[float] = []

    class Timer(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):  # noqa: ANN001
            times.append(time.perf_counter())
            cpu.append(time.process_time())
            losses.append(float(outputs["loss"]) if isinstance(outputs, dict) else float(outputs))

    trainer = L.Trainer(
        max_steps=warmup + steps, accelerator="cpu", devices=1, precision=cfg.trainer.precision, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        num_sanity_val_steps=0, callbacks=[Timer()],
    )  # fmt: skip
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=datamodule)
    timed = times[warmup:]
    per_step = (timed[-1] - times[warmup - 1]) / len(timed) if warmup else (timed[-1] - t0) / len(timed)
    return {
        "steps_per_s": 1.0 / per_step,
        "s_per_step": per_step,
        "cpu_s_per_step": (cpu[-1] - cpu[warmup - 1]) / len(timed) if warmup else float("nan"),
        "warmup_s": times[warmup - 1] - t0 if warmup else 0.0,
        "loss_first": losses[0],
        "loss_last_mean10": sum(losses[-10:]) / len(losses[-10:]),
        "peak_rss_mb": peak_rss_mb(),
        "threads": torch.get_num_threads(),
        "interop_threads": torch.get_num_interop_threads(),
    }


PHASES = ("posediff.encoder", "posediff.perturb", "posediff.denoiser", "posediff.losses", "posediff.backward")


def profile_step(overrides: list[str], steps: int, warmup: int) -> dict[str, Any]:
    """A step of the real ``Trainer.fit`` split into phases (ms) by ``torch.profiler``: the named ranges of
    ``training_step`` and of the module's ``backward``; the optimizer is Adam's step less the closure it
    runs (forward and backward); data is the time between one batch's end and the next one's start (the
    DataLoader's next batch and Lightning's hooks)."""
    import lightning as L
    import torch
    from torch.profiler import ProfilerActivity, profile, record_function

    cfg, datamodule, module = build(overrides)
    backward = module.backward

    def named_backward(loss, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        with record_function("posediff.backward"):
            return backward(loss, *args, **kwargs)

    module.backward = named_backward
    state: dict[str, Any] = {"gaps": [], "end": None, "done": 0}  # done: steps finished (over epochs)

    class Profiling(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):  # noqa: ANN001
            batch_idx = state["done"]
            if batch_idx == warmup:
                state["prof"] = profile(activities=[ProfilerActivity.CPU], with_stack=True)
                state["prof"].__enter__()
                state["t0"] = time.perf_counter()
            elif batch_idx > warmup and state["end"] is not None:
                state["gaps"].append(time.perf_counter() - state["end"])

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):  # noqa: ANN001
            state["end"] = time.perf_counter()
            batch_idx, state["done"] = state["done"], state["done"] + 1
            if batch_idx == warmup + steps - 1:
                state["wall"] = time.perf_counter() - state["t0"]
                state["prof"].__exit__(None, None, None)

    trainer = L.Trainer(
        max_steps=warmup + steps, accelerator="cpu", devices=1, precision=cfg.trainer.precision, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        num_sanity_val_steps=0, callbacks=[Profiling()],
    )  # fmt: skip
    trainer.fit(module, datamodule=datamodule)
    ranges = {k: 0.0 for k in PHASES}
    adam = group_ms = 0.0
    for e in state["prof"].events():
        if e.name in ranges:
            ranges[e.name] += e.cpu_time_total / 1e3
        elif e.name.startswith("Optimizer.step#"):
            adam += e.cpu_time_total / 1e3
        elif "posediff/lie/" in e.name and not _inside_lie(
            e
        ):  # a Python frame of the group code (with_stack)
            group_ms += e.cpu_time_total / 1e3
    phases = {k.split(".", 1)[1]: v / steps for k, v in ranges.items()}
    phases["optimizer"] = max(adam / steps - sum(phases.values()), 0.0)
    phases["data"] = 1e3 * sum(state["gaps"]) / max(len(state["gaps"]), 1)
    return {
        "ms_per_step_profiled": 1e3 * state["wall"] / steps,
        "phases_ms": phases,
        "group_math_forward_ms": group_ms / steps,
        "peak_rss_mb": peak_rss_mb(),
        "threads": torch.get_num_threads(),
    }


def _inside_lie(event: Any) -> bool:
    """``event`` runs inside another frame of ``posediff/lie/`` (counted there already)."""
    parent = event.cpu_parent
    while parent is not None:
        if "posediff/lie/" in parent.name:
            return True
        parent = parent.cpu_parent
    return False


def bf16_native() -> bool:
    """The CPU computes in bf16 natively (AVX512-BF16 or AMX), read from the CPU's flags; never assumed."""
    from posediff.hardware import native_bf16

    return native_bf16()


def fit_curve(overrides: list[str], steps: int) -> dict[str, Any]:
    """``steps`` steps of ``Trainer.fit`` then the held-out DSM loss (``val/loss``, the validation split's
    first 8 batches at fixed noise draws), and the training losses every 50 steps."""
    import lightning as L

    cfg, datamodule, module = build([*overrides, f"trainer.max_steps={steps}"])
    losses: list[float] = []

    class Curve(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):  # noqa: ANN001
            losses.append(float(outputs["loss"]) if isinstance(outputs, dict) else float(outputs))

    trainer = L.Trainer(
        max_steps=steps, accelerator="cpu", devices=1, precision=cfg.trainer.precision, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        num_sanity_val_steps=0, callbacks=[Curve()],
    )  # fmt: skip
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=datamodule)
    seconds = time.perf_counter() - t0
    judge = L.Trainer(accelerator="cpu", devices=1, logger=False, limit_val_batches=8, enable_progress_bar=False,
                      enable_model_summary=False)  # fmt: skip
    (val,) = judge.validate(module, datamodule=datamodule, verbose=False)
    return {"val_loss": float(val["val/loss"]), "train_loss_every_50": losses[49::50], "seconds": seconds}


def ab_steps(configs: dict[str, list[str]], rounds: int, warmup: int) -> dict[str, Any]:
    """Whole training steps (``training_step``, backward, Adam, zero_grad) of several configurations of one
    experiment, **interleaved** — one step of each in turn, ``rounds`` times — on the same batch: a busy
    host slows them all alike, so their ratio holds where back-to-back runs differ by ±15 %. Median ms."""
    import statistics

    import lightning as L
    import torch

    built = {}
    batch = None
    for name, overrides in configs.items():
        cfg, datamodule, module = build(overrides)
        module.trainer = L.Trainer(max_steps=int(cfg.trainer.max_steps), logger=False, accelerator="cpu", devices=1,
                                   enable_progress_bar=False, enable_model_summary=False)  # fmt: skip
        module.log = lambda *a, **k: None
        opt = module.configure_optimizers()["optimizer"]
        module.train()
        module.on_fit_start()
        if batch is None:
            batch = next(iter(datamodule.train_dataloader()))
        bf16 = "bf16" in str(cfg.trainer.precision)
        built[name] = (module, opt, bf16)
    times: dict[str, list[float]] = {k: [] for k in built}
    cpu: dict[str, list[float]] = {k: [] for k in built}
    for r in range(warmup + rounds):
        for name, (module, opt, bf16) in built.items():
            t, c = time.perf_counter(), time.process_time()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):  # as Lightning's bf16-mixed
                loss = module.training_step(batch, r)
            loss.backward()
            opt.step()
            opt.zero_grad(set_to_none=True)
            if r >= warmup:
                times[name].append(time.perf_counter() - t)
                cpu[name].append(time.process_time() - c)
    return {
        name: {
            "ms_median": 1e3 * statistics.median(v),
            "ms_all": [1e3 * x for x in v],
            "cpu_ms_median": 1e3 * statistics.median(cpu[name]),
        }  # fmt: skip
        for name, v in times.items()
    }


def worker(spec: dict[str, Any]) -> dict[str, Any]:
    if spec["kind"] == "ab":
        return ab_steps(spec["configs"], spec["rounds"], spec["warmup"])
    if spec["kind"] == "curve":
        return fit_curve(spec["overrides"], spec["steps"])
    if spec["kind"] == "profile":
        return profile_step(spec["overrides"], spec["steps"], spec["warmup"])
    return fit_speed(spec["overrides"], spec["steps"], spec["warmup"])


def run_worker(spec: dict[str, Any], threads: int | None) -> dict[str, Any]:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True, text=True,
                          cwd=ROOT, env=env)  # fmt: skip
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}",
                "wall_s": time.perf_counter() - t}  # fmt: skip
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - t
    return out


# --------------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------------


def markdown(results: dict[str, Any]) -> str:
    meta = results["machine"]
    lines = [
        "# One training step: where the time goes, and the levers",
        "",
        f"`{results['command']}` — {meta['cpu']}, {meta['cores']} cores, torch {meta['torch']}, "
        f"bf16 native: {meta['bf16_native']}; {results['steps']} timed steps after {results['warmup']}.",
        "",
    ]
    for name, exp in results["experiments"].items():
        prof = exp.get("profile", {})
        if "phases_ms" in prof:
            lines += [f"## {name}: one step ({prof['ms_per_step_profiled']:.0f} ms profiled)", "",
                      "| phase | ms | share |", "|---|---|---|"]  # fmt: skip
            total = sum(prof["phases_ms"].values()) or 1.0
            for k, v in prof["phases_ms"].items():
                lines.append(f"| {k} | {v:.1f} | {100 * v / total:.0f} % |")
            lines += [f"| (group math, forward, inside the above) | {prof['group_math_forward_ms']:.1f} | |",
                      "", f"peak memory {prof['peak_rss_mb']:.0f} MB", ""]  # fmt: skip
        inter = exp.get("interleaved", {})
        if "today" in inter:
            t0 = inter["today"]["ms_median"]
            lines += [f"## {name}: interleaved steps (one of each in turn, {len(inter['today']['ms_all'])} rounds, same batch)",
                      "", "| configuration | ms/step (median) | × today's speed | CPU ms/step |", "|---|---|---|---|"]  # fmt: skip
            for k, v in inter.items():
                if isinstance(v, dict) and "ms_median" in v:
                    lines.append(
                        f"| {k} | {v['ms_median']:.0f} | {t0 / v['ms_median']:.2f} | {v['cpu_ms_median']:.0f} |"
                    )
            lines.append("")
        base = exp.get("levers", {}).get("today", {}).get("steps_per_s")
        lines += [f"## {name}: levers (Lightning fit, back to back)", "", "| lever | steps/s (rounds) | × today | CPU s/step | warm-up s | peak MB | what |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for lever, r in exp.get("levers", {}).items():
            if "steps_per_s" in r:
                ratio = f"{r['steps_per_s'] / base:.2f}" if base else "–"
                what = LEVERS[lever][0] if lever in LEVERS else {
                    "best": "the winners together: " + ", ".join(exp.get("best_levers", [])),
                    "defaults": "posediff fit's settings now (conf/fit.yaml)"}.get(lever, "")  # fmt: skip
                rounds = ", ".join(f"{x:.2f}" for x in r.get("steps_per_s_rounds", []))
                lines.append(f"| {lever} | {r['steps_per_s']:.2f} ({rounds}) | {ratio} | {r.get('cpu_s_per_step', 0):.2f} | "
                             f"{r['warmup_s']:.0f} | {r['peak_rss_mb']:.0f} | {what} |")  # fmt: skip
            else:
                lines.append(f"| {lever} | – | – | – | – | – | {r.get('skipped') or r.get('error')} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def _median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run with the median steps/s (the lower middle one of an even count), with every round's value."""
    ok = sorted((r for r in runs if "steps_per_s" in r), key=lambda r: r["steps_per_s"])
    if not ok:
        return dict(runs[-1])
    out = dict(ok[(len(ok) - 1) // 2])
    out["steps_per_s_rounds"] = [r["steps_per_s"] for r in runs if "steps_per_s" in r]
    return out


def curve(args: argparse.Namespace, results: dict[str, Any]) -> int:
    """Equal learning: the held-out loss after ``--curve`` steps of two code paths (``--curve-paths``;
    today's against the defaults unless told), seeds 0 and 1: equal when the paths differ by no more
    than the seeds do."""
    out = (
        RESULTS / "train_step_curve.json" if args.out == str(RESULTS / "train_step.json") else Path(args.out)
    )
    results["curve_steps"] = args.curve
    results["runs"] = {}
    name = args.only[0]
    base_path, new_path = args.curve_paths
    results["curve_paths"] = [base_path, new_path]
    for seed in (0, 1):
        for path in (base_path, new_path):
            extra = CURVE_PATHS[path]
            spec = {
                "kind": "curve",
                "overrides": [*EXPERIMENTS[name], *extra, f"seed={seed}"],
                "steps": args.curve,
            }
            r = run_worker(spec, None)
            results["runs"][f"{path}_seed{seed}"] = r
            print(name, path, seed, json.dumps(r), flush=True)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.with_suffix(".tmp").write_text(json.dumps(results, indent=2) + "\n")
            out.with_suffix(".tmp").replace(out)
    v = {k: r.get("val_loss") for k, r in results["runs"].items()}
    if all(x is not None for x in v.values()):
        seed_gap = abs(v[f"{base_path}_seed0"] - v[f"{base_path}_seed1"])
        path_gap = max(
            abs(v[f"{base_path}_seed0"] - v[f"{new_path}_seed0"]),
            abs(v[f"{base_path}_seed1"] - v[f"{new_path}_seed1"]),
        )
        results["verdict"] = {
            "seed_gap": seed_gap,
            "path_gap": path_gap,
            "equal_within_seed_noise": path_gap <= seed_gap,
        }
        out.write_text(json.dumps(results, indent=2) + "\n")
        print(json.dumps(results["verdict"]))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--only", nargs="*", choices=list(EXPERIMENTS), default=list(EXPERIMENTS))
    ap.add_argument(
        "--levers", nargs="*", choices=[*LEVERS, "best", "defaults"], default=[*LEVERS, "best", "defaults"]
    )
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=2, help="rounds over the levers, interleaved (median)")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--no-profile", action="store_true")
    ap.add_argument(
        "--ab",
        type=int,
        default=20,
        metavar="ROUNDS",
        help="interleaved whole steps of today / the defaults / each Adam and layout lever (0: off)",
    )
    ap.add_argument("--curve", type=int, default=0, metavar="STEPS",
                    help="instead: today's code path and posediff's defaults, seeds 0 and 1, STEPS steps each; "
                    "the held-out loss after them (writes train_step_curve.json)")  # fmt: skip
    ap.add_argument(
        "--curve-paths",
        nargs=2,
        choices=list(CURVE_PATHS),
        default=["today", "defaults"],
        metavar=("BASE", "NEW"),
        help=f"the two code paths --curve compares ({', '.join(CURVE_PATHS)})",
    )
    ap.add_argument("--out", default=str(RESULTS / "train_step.json"))
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return 0
    import torch

    ensure_data()
    out = Path(args.out)
    results: dict[str, Any] = {
        "command": "python benchmarks/train_step.py " + " ".join(sys.argv[1:]),
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "torch": torch.__version__,
            "bf16_native": bf16_native(),
        },  # fmt: skip
        "steps": args.steps,
        "warmup": args.warmup,
        "experiments": {},
    }

    def save() -> None:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(results, indent=2) + "\n")
        tmp.replace(out)
        md = out.with_suffix(".md")
        md.with_suffix(".md.tmp").write_text(markdown(results))
        md.with_suffix(".md.tmp").replace(md)

    if args.curve:
        return curve(args, results)
    for name in args.only:
        exp: dict[str, Any] = {"overrides": EXPERIMENTS[name], "levers": {}}
        results["experiments"][name] = exp
        if args.ab:
            configs = {"today": [*EXPERIMENTS[name], *TODAY], "defaults": list(EXPERIMENTS[name])}
            for lever in ("foreach_adam", "fused_adam", "channels_last", "fused_channels_last"):
                configs[lever] = [*EXPERIMENTS[name], *TODAY, *LEVERS[lever][1]]
            if bf16_native():
                configs["bf16"] = [*EXPERIMENTS[name], *TODAY, *LEVERS["bf16"][1]]
                configs["defaults_bf16"] = [*EXPERIMENTS[name], *LEVERS["bf16"][1]]
            exp["interleaved"] = run_worker(
                {"kind": "ab", "configs": configs, "rounds": args.ab, "warmup": 3}, None
            )
            print(name, "interleaved", json.dumps({k: v.get("ms_median") for k, v in exp["interleaved"].items()
                                                   if isinstance(v, dict)}), flush=True)  # fmt: skip
            save()
        if not args.no_profile:
            spec = {"kind": "profile", "overrides": EXPERIMENTS[name], "steps": max(args.steps // 3, 5),
                    "warmup": 3}  # fmt: skip
            exp["profile"] = run_worker(spec, None)
            print(name, "profile", json.dumps(exp["profile"]), flush=True)
            save()
        runs: dict[str, list[dict[str, Any]]] = {}
        for round_ in range(args.repeats):
            for lever in args.levers:
                if lever == "best" and round_ == 0 and args.repeats > 1:
                    continue  # the winners are known after the first round
                if lever == "best":
                    base = exp["levers"].get("today", {}).get("steps_per_s")
                    wins = [k for k, r in exp["levers"].items() if k in LEVERS and k != "today" and base and
                        r.get("steps_per_s", 0) > 1.03 * base]  # fmt: skip
                    winners = [o for k in wins for o in LEVERS[k][1]]
                    keys = [o.split("=")[0] for o in winners]
                    if len(set(keys)) != len(keys):  # foreach and fused both won: the faster one
                        adam = max(
                            (k for k in wins if k.endswith("_adam")),
                            key=lambda k: exp["levers"][k]["steps_per_s"],
                        )
                        wins = [k for k in wins if not k.endswith("_adam") or k == adam]
                        winners = [o for k in wins for o in LEVERS[k][1]]
                    overrides = [*EXPERIMENTS[name], *TODAY, *winners]
                    exp["best_levers"] = wins
                elif lever == "defaults":
                    overrides = list(EXPERIMENTS[name])
                else:
                    overrides = [*EXPERIMENTS[name], *TODAY, *LEVERS[lever][1]]
                spec = {"kind": "fit", "overrides": overrides, "steps": args.steps, "warmup": args.warmup}
                runs.setdefault(lever, []).append(run_worker(spec, None))
                exp["levers"][lever] = _median_run(runs[lever])
                exp["levers"][lever]["overrides"] = overrides
                print(name, lever, round_, json.dumps(runs[lever][-1]), flush=True)
                save()
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
