"""What makes orientation learn soonest from images on a CPU: a study of encoder- and denoiser-side levers.

Each variant is one ``posediff fit +experiment=quickstart ...`` run with a few overrides (the exact
command is stored with its result). For every run it records, from the run's ``metrics.json`` and
its CSV log:

* the held-out rotation part of the DSM loss (``val/rotation_loss``) and the whole held-out loss at
  every validation;
* the probe "does the encoder see orientation": the anchor's symmetry-aware rotation error on the
  held-out batches (``val/anchor_deg``; variants with a pose head);
* the encoder's gradient norm from the rotation and translation parts of the diffusion loss
  (``grad/encoder_rotation`` / ``grad/encoder_translation``, every ``--probe-every`` steps);
* the final spread, R@10° and coverage per shape, the translation error, the wall time.

Also, once: the schedule's share of levels below 0.1 / 0.35 rad and whether its top level reaches
the Haar prior the samplers start from.

    python benchmarks/learning_speed.py --parallel 2          # every variant, 1000 steps (≈ 45 min on 2 cores)
    python benchmarks/learning_speed.py --only quickstart paper --steps 1000
    python benchmarks/learning_speed.py --list
    python benchmarks/learning_speed.py --steps 2500 --out benchmarks/results/learning_speed_2500.json   # the demo's budget

Results go to ``benchmarks/results/learning_speed.json`` (updated after every run, so an
interrupted study keeps what finished) and a Markdown table next to it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
POSEDIFF = [sys.executable, "-m", "posediff.cli"]

D64 = ["data.root=data/symsolt_uniform_cpu", "data.image_size=64"]
D128 = ["data.root=data/symsolt_scene2_cpu128", "data.image_size=128"]
WHOLE = ["encoder.crop_size=null"]
SIXD = ["encoder.rotation_head=6d"]
PAPER_INPUT = ["module.anchor=false", "module.aux_weight=0.0"]
DIFFUSION_ONLY = ["module.aux_weight=0.0"]
REGRESSION = ["module._target_=posediff.models.PoseRegressionModule", "module.denoiser=null"]
OLD = ["module.lr=3e-4", "module.lr_final=3e-5", "schedule.noise_end=1.0"]
#: the quickstart before the symmetry-fold study (16 images x 64 noisy poses, depth regressed, unfolded):
#: the base every variant below was measured against, so each variant pins it (its own overrides win)
PREVIOUS = [
    "data.batch_size=16",
    "module.num_noisy=64",
    "encoder.depth_cue=null",
    "module.symmetry_fold=false",
]

#: name → (what it tests, overrides of ``+experiment=quickstart``: locate-then-crop from 128 px, the
#: invariant head, anchored + auxiliary loss, R³×SO(3), Adam 1e-4 / denoiser 1e-3, σ_max 1.97 rad)
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "paper": (
        "the previous quickstart: the paper's model on the whole 64 px image (input Log X̃, Adam 3e-4, "
        "σ_max 0.985); 6-D pose head as a linear probe",
        D64 + WHOLE + SIXD + PAPER_INPUT + OLD,
    ),
    "crop_paper_input": (
        "locate-then-crop, the paper's input Log X̃ (invariant head as a linear probe)",
        PAPER_INPUT,
    ),
    "crop_anchor_6d": (
        "locate-then-crop, anchored, diffusion loss only (no symmetry labels; 6-D anchor)",
        SIXD + DIFFUSION_ONLY,
    ),
    "crop_anchor_aux_6d": ("locate-then-crop, anchored + auxiliary loss, 6-D head", SIXD),
    "previous_quickstart": (
        "locate-then-crop, anchored + auxiliary loss, invariant head at one spread per shape, 16 x 64 "
        "(the quickstart before the symmetry-fold study)",
        [],
    ),
    "quickstart_raw": (
        "the same with the invariant head's raw targets (quickstart before issue 27: encoder.embedding_scale=raw)",
        ["encoder.embedding_scale=raw"],
    ),
    "quickstart_64px": ("the same from 64 px images (crop 64 px upsampled)", D64),
    "quickstart_lr3e-4": (
        "the same with the encoder at Adam 3e-4 → 3e-5",
        ["module.lr=3e-4", "module.lr_final=3e-5"],
    ),
    "quickstart_se3": ("the same on SE(3)", ["group=se3"]),
    "quickstart_one_lr": ("the same with the denoiser at the encoder's 1e-4", ["module.denoiser_lr=null"]),
    "quickstart_size_depth": (
        "the same with the pose head's depth from the apparent size (encoder.depth_cue=size_head)",
        ["encoder.depth_cue=size_head"],
    ),
    "quickstart_ema_0.99": (
        "the same, evaluated with an EMA of the weights, decay 0.99 every 5 steps (a window of ~500 steps)",
        ["ema=authors", "ema.decay=0.99"],
    ),
    "quickstart_ema_authors": (
        "the same with the authors' EMA, decay 0.999 every 5 steps (a window of ~5000 steps)",
        ["ema=authors"],
    ),
    "quickstart_b32_n32": (
        "images per batch against noisy poses per image: 32 images x 32 noisy poses (quickstart: 16 x 64)",
        ["data.batch_size=32", "module.num_noisy=32"],
    ),
    "quickstart_b32_n32_size": (
        "32 images x 32 noisy poses with the depth from the apparent size (encoder.depth_cue=size_head)",
        ["data.batch_size=32", "module.num_noisy=32", "encoder.depth_cue=size_head"],
    ),
    "quickstart_b32_n32_size_fold": (
        "the same with the symmetry-folded denoiser (module.symmetry_fold=true: it sees the noisy pose's "
        "equivalent nearest the anchor) = the quickstart now",
        [
            "data.batch_size=32",
            "module.num_noisy=32",
            "encoder.depth_cue=size_head",
            "module.symmetry_fold=true",
        ],
    ),
    "quickstart_se3_fold": (
        "the quickstart now (32 x 32, size_head, folded) on SE(3)",
        [
            "data.batch_size=32",
            "module.num_noisy=32",
            "encoder.depth_cue=size_head",
            "module.symmetry_fold=true",
            "group=se3",
        ],  # fmt: skip
    ),
    "quickstart_area_coverage": (
        "the quickstart now with the apparent size measured by edge coverage (encoder.area_estimate=coverage)",
        [
            "data.batch_size=32",
            "module.num_noisy=32",
            "encoder.depth_cue=size_head",
            "module.symmetry_fold=true",
            "encoder.area_estimate=coverage",
        ],  # fmt: skip
    ),
    "quickstart_depth_embedding": (
        "the quickstart now with the depth offset also from an MLP of the invariant embeddings "
        "(encoder.depth_head=embedding)",
        [
            "data.batch_size=32",
            "module.num_noisy=32",
            "encoder.depth_cue=size_head",
            "module.symmetry_fold=true",
            "encoder.depth_head=embedding",
        ],  # fmt: skip
    ),
    "quickstart_render": (
        "rendered on the fly, 8000 poses per shape: no image repeats in 2500 steps (quickstart: 10 000 fixed)",
        ["data.mode=render", "data.n_per_shape_train=8000"],
    ),
    "iterative_regression": (
        "locate-then-crop, the iterative-regression baseline (Table 2): the pose head refined 4 times by the MLP",
        ["module._target_=posediff.models.PoseRegressionModule", "+module.iterations=4"],
    ),
    "regression_6d": (
        "locate-then-crop, the regression baseline, 6-D head (min over the symmetries)",
        SIXD + REGRESSION,
    ),
    "regression_invariant": ("locate-then-crop, the regression baseline, invariant head", REGRESSION),
}


def _pinned(overrides: list[str]) -> list[str]:
    """:data:`PREVIOUS` with ``overrides`` on top (one value per key, the variant's winning)."""
    merged = dict(o.split("=", 1) for o in PREVIOUS)
    merged.update(o.split("=", 1) for o in overrides)
    return [f"{k}={v}" for k, v in merged.items()]


VARIANTS = {name: (what, _pinned(ov)) for name, (what, ov) in VARIANTS.items()}


def schedule_report(overrides: tuple[str, ...] = ()) -> dict[str, float | bool]:
    """The quickstart schedule's share of levels below 0.1 / 0.35 rad and its top level vs the prior."""
    import torch
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from posediff.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=quickstart", *overrides])
    sched = instantiate(cfg.schedule)
    sig = sched.sigma(torch.arange(sched.num_levels), dtype=torch.float64)
    from posediff.diffusion import ConcentratedGaussian
    from posediff.lie import SO3

    kernel = ConcentratedGaussian(SO3())
    g = torch.Generator().manual_seed(0)
    _, z = kernel.sample(
        SO3().identity((20000,), dtype=torch.float64),
        torch.full((20000,), float(sig.max()), dtype=torch.float64),
        generator=g,
    )
    top_angle = float(SO3().log(SO3().exp(z)).norm(dim=-1).mean())
    haar = SO3().sample_uniform((20000,), dtype=torch.float64, generator=g)
    haar_angle = float(SO3().log(haar).norm(dim=-1).mean())
    return {
        "schedule": sched.name,
        "num_levels": int(sched.num_levels),
        "sigma_max": float(sig.max()),
        "share_below_0.1": float((sig < 0.1).double().mean()),
        "share_below_0.35": float((sig < 0.35).double().mean()),
        "top_level_mean_angle_rad": top_angle,
        "haar_mean_angle_rad": haar_angle,
        "top_reaches_prior": bool(abs(top_angle - haar_angle) < 0.05 * haar_angle),
    }


def _read_log(run_dir: Path) -> dict[str, list[list[float]]]:
    """``metric → [[step, value], ...]`` from the run's CSV log."""
    path = run_dir / "logs" / "metrics.csv"
    out: dict[str, list[list[float]]] = {}
    if not path.is_file():
        return out
    with path.open() as f:
        for row in csv.DictReader(f):
            step = row.get("step")
            for k, v in row.items():
                if k in ("step", "epoch") or v in (None, ""):
                    continue
                if k.startswith(("val/", "grad/")) or k == "train/anchor_deg":
                    out.setdefault(k, []).append([float(step), float(v)])
    return out


def run_variant(
    name: str, steps: int, probe_every: int, threads: int, extra: list[str], study: str = "learning_speed"
) -> dict:
    """One variant's run in ``outputs/<study>/<name>`` (``study``: the results file's stem)."""
    what, overrides = VARIANTS[name]
    run_dir = ROOT / "outputs" / study / name
    args = [
        "fit",
        "+experiment=quickstart",
        *overrides,
        f"trainer.max_steps={steps}",
        "trainer.val_check_interval=250",
        "trainer.enable_progress_bar=false",
        f"module.grad_probe_every={probe_every}",
        "eval.before=false",
        *extra,
        f"hydra.run.dir={run_dir}",
    ]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), OMP_WAIT_POLICY="PASSIVE")
    start = time.perf_counter()
    log = run_dir.with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as f:
        code = subprocess.call([*POSEDIFF, *args], cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=env)
    wall = time.perf_counter() - start
    result: dict = {
        "what": what,
        "command": "posediff " + " ".join(args[:-1]),
        "exit_code": code,
        "wall_s": wall,
    }
    metrics = run_dir / "metrics.json"
    if code == 0 and metrics.is_file():
        m = json.loads(metrics.read_text())
        result["train"] = m.get("train")
        after = next(iter(m["after"].values()))
        res = next(iter(after.values()))
        result["eval"] = {
            "shapes": res["shapes"],
            "overall": res["overall"],
            "num_steps": res["num_steps"],
            "num_samples": res["num_samples"],
        }
    result["curves"] = _read_log(run_dir)
    return result


def _fmt(x: float | None, digits: int = 1) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _last(curves: dict, key: str) -> float | None:
    v = curves.get(key, [])
    return v[-1][1] if v else None


def _mean(curves: dict, key: str) -> float | None:
    v = [x for _, x in curves.get(key, [])]
    return sum(v) / len(v) if v else None


def markdown(results: dict) -> str:
    lines = [
        "| variant | steps | train s | held-out anchor ° (every 250 steps) | anchor tet / cube / cone / cyl ° | "
        "val rot. loss | spread tet / cube / icosa / cone / cyl ° | R@10° | cube cov. | t err | enc. grad rot / trans |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.get("runs", {}).items():
        if "eval" not in r:
            lines.append(f"| {name} | – | – | failed (exit {r.get('exit_code')}) | | | | | | | |")
            continue
        sh, c = r["eval"]["shapes"], r["curves"]
        anchor = c.get("val/anchor_deg", [])
        per_shape = " / ".join(_fmt(_last(c, f"val/anchor_deg_{s}")) for s in ("tet", "cube", "cone", "cyl"))
        spreads = " / ".join(
            _fmt(sh.get(s, {}).get("spread_deg")) for s in ("tet", "cube", "icosa", "cone", "cyl")
        )
        grads = (
            f"{_fmt(_mean(c, 'grad/encoder_rotation'), 2)} / {_fmt(_mean(c, 'grad/encoder_translation'), 2)}"
        )
        lines.append(
            f"| {name} | {r['train']['steps']} | {r['train']['seconds']:.0f} | "
            f"{' → '.join(_fmt(v) for _, v in anchor) if anchor else '–'} | {per_shape} | "
            f"{_fmt(_last(c, 'val/rotation_loss'), 2)} | {spreads} | {_fmt(r['eval']['overall'].get('recall_rot@10'), 3)} | "
            f"{_fmt(sh.get('cube', {}).get('coverage'), 2)} | {_fmt(r['eval']['overall'].get('translation_error'), 3)} | {grads} |"
        )
    if results.get("note"):
        lines.append(f"\n{results['note']}")
    for key in ("schedule_before", "schedule"):
        sched = results.get(key)
        if not sched:
            continue
        lines.append(
            f"\nSchedule ({sched['schedule']}, {sched['num_levels']} levels, σ_max {sched['sigma_max']:.3f}): "
            f"{100 * sched['share_below_0.1']:.0f} % of the levels below 0.1 rad, {100 * sched['share_below_0.35']:.0f} % "
            f"below 0.35 rad; top level's mean rotation angle {sched['top_level_mean_angle_rad']:.2f} rad vs the Haar "
            f"prior's {sched['haar_mean_angle_rad']:.2f} (reaches the prior: {sched['top_reaches_prior']})"
            + (" — the previous quickstart." if key == "schedule_before" else " — quickstart now.")
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="variants to run (default: all)")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--probe-every", type=int, default=100)
    parser.add_argument("--parallel", type=int, default=1, help="runs at a time (threads split between them)")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads per run (default: 2 / parallel)"
    )
    parser.add_argument("--out", default=str(RESULTS / "learning_speed.json"))
    parser.add_argument("--list", action="store_true")
    parser.add_argument(
        "extra",
        nargs="*",
        default=["eval.num_samples=50", "eval.num_steps=[50]"],
        help="overrides for every run (default: eval.num_samples=50 eval.num_steps=[50])",
    )
    a = parser.parse_args()
    if a.list:
        for k, (what, ov) in VARIANTS.items():
            print(f"{k:28s} {what}\n{'':28s} {' '.join(ov)}")
        return 0
    names = a.only or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        print(f"unknown variants {unknown}; available: {', '.join(VARIANTS)}", file=sys.stderr)
        return 2
    needed = {("data/symsolt_scene2_cpu128", "128")}  # quickstart's; a variant may read other shards
    for n in names:
        ov = dict(o.split("=", 1) for o in VARIANTS[n][1])
        if "data.root" in ov:
            needed.add((ov["data.root"], ov.get("data.image_size", "128")))
    for root, size in sorted(needed):
        if not (ROOT / root / "test" / "index.npz").is_file():
            print(
                f"learning_speed: {root} is missing; make it with: posediff data render dataset=symsolt split=train "
                f"image_size={size} out={root} && posediff data render dataset=symsolt split=test image_size={size} out={root}",
                file=sys.stderr,
            )
            return 2
    threads = a.threads or max(1, 2 // max(a.parallel, 1))
    out = Path(a.out)
    results = json.loads(out.read_text()) if out.is_file() else {}
    results["schedule"] = schedule_report()
    results["schedule_before"] = schedule_report(("schedule.noise_end=1.0",))
    results.setdefault("runs", {})
    lock = threading.Lock()

    def one(name: str) -> None:
        print(f"[learning_speed] {name}: {VARIANTS[name][0]}", flush=True)
        r = run_variant(name, a.steps, a.probe_every, threads, a.extra, out.stem)
        with lock:  # merge with what is on disk (other runs, other study processes), write atomically
            disk = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
            disk.setdefault("runs", {})[name] = r
            disk["schedule"], disk["schedule_before"] = results["schedule"], results["schedule_before"]
            tmp = out.with_suffix(".tmp")
            tmp.write_text(json.dumps(disk, indent=1))
            tmp.replace(out)
            out.with_suffix(".md").write_text(markdown(disk))
            print(markdown({"runs": {name: r}}), flush=True)

    with ThreadPoolExecutor(max_workers=max(a.parallel, 1)) as pool:
        list(pool.map(one, names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
