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

    python benchmarks/learning_speed.py                       # every variant (hours on 2 cores)
    python benchmarks/learning_speed.py --only crop128_anchor_aux paper --steps 1500
    python benchmarks/learning_speed.py --list

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
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
POSEDIFF = [sys.executable, "-m", "posediff.cli"]

D64 = ["data.root=data/symsolt_uniform_cpu", "data.image_size=64"]
D128 = ["data.root=data/symsolt_uniform_cpu128", "data.image_size=128"]
POSE = ["encoder=pose"]
CROP = ["encoder.crop_size=64"]

#: name → (what it tests, overrides of ``+experiment=quickstart``)
ANCHOR = ["module.anchor=true"]
AUX = ["module.anchor=true", "module.aux_weight=1.0"]
REGRESSION = ["module._target_=posediff.regression.PoseRegressionModule", "module.denoiser=null"]
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "paper": ("the paper's model (whole 64 px image, input Log X̃), pose head as a linear probe", D64 + POSE),
    "anchor_aux_64": ("anchored + auxiliary loss, whole 64 px image (no crop)", D64 + POSE + AUX),
    "crop64_anchor_aux": (
        "locate-then-crop from 64 px images, anchored + auxiliary loss",
        D64 + POSE + CROP + AUX,
    ),
    "crop128_paper_input": (
        "locate-then-crop from 128 px images, the paper's input Log X̃ (linear probe)",
        D128 + POSE + CROP,
    ),
    "crop128_anchor": (
        "locate-then-crop from 128 px, anchored, diffusion loss only (no symmetry labels)",
        D128 + POSE + CROP + ANCHOR,
    ),
    "crop128_anchor_aux": (
        "locate-then-crop from 128 px, anchored + auxiliary loss",
        D128 + POSE + CROP + AUX,
    ),
    "crop128_regression": (
        "locate-then-crop from 128 px, regression baseline",
        D128 + POSE + CROP + REGRESSION,
    ),
    "crop128_anchor_aux_r3so3": (
        "as crop128_anchor_aux on R³×SO(3)",
        D128 + POSE + CROP + AUX + ["group=r3so3"],
    ),
    "crop128_anchor_aux_lr1e-4": (
        "as crop128_anchor_aux at Adam 1e-4 → 1e-5",
        D128 + POSE + CROP + AUX + ["module.lr=1e-4", "module.lr_final=1e-5"],
    ),
    "crop128_anchor_aux_pretrained": (
        "as crop128_anchor_aux, encoder from `posediff pretrain` (data/pretrained/symsolt_resnet18_crop64.pt)",
        D128 + POSE + CROP + AUX + ["encoder.weights=data/pretrained/symsolt_resnet18_crop64.pt"],
    ),
}


def schedule_report() -> dict[str, float | bool]:
    """The quickstart schedule's share of levels below 0.1 / 0.35 rad and its top level vs the prior."""
    import torch
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from posediff.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=quickstart"])
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


def run_variant(name: str, steps: int, probe_every: int, threads: int, extra: list[str]) -> dict:
    what, overrides = VARIANTS[name]
    run_dir = ROOT / "outputs" / "learning_speed" / name
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


def markdown(results: dict) -> str:
    lines = [
        "| variant | steps | train s | anchor ° (held out) | val rot. loss | tet / cube / icosa / cone / cyl spread ° | R@10° | cube cov. | t err |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.get("runs", {}).items():
        if "eval" not in r:
            lines.append(f"| {name} | – | – | failed (exit {r.get('exit_code')}) | | | | | |")
            continue
        sh = r["eval"]["shapes"]
        anchor = r["curves"].get("val/anchor_deg", [])
        rl = r["curves"].get("val/rotation_loss", [])
        spreads = " / ".join(
            _fmt(sh.get(s, {}).get("spread_deg")) for s in ("tet", "cube", "icosa", "cone", "cyl")
        )
        lines.append(
            f"| {name} | {r['train']['steps']} | {r['train']['seconds']:.0f} | "
            f"{' → '.join(_fmt(v) for _, v in anchor[::2] + anchor[-1:]) if anchor else '–'} | "
            f"{_fmt(rl[-1][1], 2) if rl else '–'} | {spreads} | {_fmt(r['eval']['overall'].get('recall_rot@10'), 3)} | "
            f"{_fmt(sh.get('cube', {}).get('coverage'), 2)} | {_fmt(r['eval']['overall'].get('translation_error'), 3)} |"
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="variants to run (default: all)")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--probe-every", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default=str(RESULTS / "learning_speed.json"))
    parser.add_argument("--list", action="store_true")
    parser.add_argument("extra", nargs="*", help="overrides for every run (e.g. eval.num_samples=50)")
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
    out = Path(a.out)
    results = json.loads(out.read_text()) if out.is_file() else {}
    results.setdefault("schedule", schedule_report())
    results.setdefault("runs", {})
    for name in names:
        print(f"[learning_speed] {name}: {VARIANTS[name][0]}", flush=True)
        r = run_variant(name, a.steps, a.probe_every, a.threads, a.extra)
        results["runs"][name] = r
        if out.is_file():  # another study process may have written meanwhile: merge
            disk = json.loads(out.read_text())
            disk.setdefault("runs", {}).update({name: r})
            results = {**disk, "schedule": results["schedule"]}
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(out)
        out.with_suffix(".md").write_text(markdown(results))
        print(markdown({"runs": {name: r}}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
