"""The symmetric-shape toy, every variant of the paper's ablations, on the CPU.

    python benchmarks/toy.py                 # train + evaluate every variant, one after another
    python benchmarks/toy.py --only se3_autograd --max-steps 500   # one variant, shorter
    python benchmarks/toy.py --collect       # rebuild the table from finished runs
    python benchmarks/toy.py --max-steps 3000   # the ablation budget: runs in outputs/toy_3000/,
                                                # results in benchmarks/results/toy_3000.{json,md}

Each variant is one ``posediff fit +experiment=toy_*`` run (Hydra overrides below), trained for
``trainer.max_steps`` and evaluated with the random walk, the ancestral and the few-step sampler
(deterministic, and with full re-noising) at 5 / 10 / 50 / 100 steps (200 samples for each of 4
test conditions per shape). Runs go to ``outputs/toy/<variant>/`` (metrics.json there); the
collected results go to ``benchmarks/results/toy.json`` and the markdown table to
``benchmarks/results/toy.md`` (``toy_<steps>`` for a ``--max-steps`` budget).

On one core a 5000-step SO(3) variant takes about 12 min to train and 6 min to evaluate, an SE(3)
one about 15 + 8 min; 15000 steps took 34 min of training for SO(3).

Variants (what the paper compares, Tables 5–6 and the supplement):

* ``so3_surrogate`` — SO(3), concentrated Gaussian N, surrogate score, Fourier blocks (reference);
* ``so3_scale_bias`` — the same with scale-bias (FiLM) blocks instead of Fourier blocks;
* ``so3_igso3`` — IG_SO(3) noise with its exact (closed-form) score instead of N;
* ``se3_surrogate`` / ``se3_closed_form`` / ``se3_autograd`` — SE(3) with the three score targets;
* ``se3_matrix`` — beyond the paper: the network sees the entries of X̃ instead of the twist Log X̃.
"""

import argparse
import datetime as dt
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"

VARIANTS: dict[str, list[str]] = {
    "so3_surrogate": ["+experiment=toy_so3"],
    "so3_scale_bias": ["+experiment=toy_so3", "denoiser.block=scale_bias"],
    "so3_igso3": ["+experiment=toy_so3", "kernel=igso3", "diffusion.score=closed_form"],
    "se3_surrogate": ["+experiment=toy_se3"],
    "se3_closed_form": ["+experiment=toy_se3", "diffusion.score=closed_form"],
    "se3_autograd": ["+experiment=toy_se3", "diffusion.score=autograd"],
    "se3_matrix": ["+experiment=toy_se3", "module.pose_input=matrix"],
}
DISCRETE = ("tet", "cube", "icosa")


def _names(max_steps: int | None) -> tuple[Path, Path]:
    """(runs folder, results JSON) for the experiment's own budget or an overridden one."""
    tag = "toy" if max_steps is None else f"toy_{max_steps}"
    return ROOT / "outputs" / tag, RESULTS_DIR / f"{tag}.json"


def run_variant(name: str, extra: list[str], runs_dir: Path) -> Path:
    out = runs_dir / name
    exe = Path(sys.executable).with_name("posediff")
    cmd = [str(exe), "fit", *VARIANTS[name], *extra, f"hydra.run.dir={out}"]
    print("$", " ".join(cmd[1:]), flush=True)
    log = out.with_suffix(".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    return out / "metrics.json"


def collect(runs_dir: Path, previous: Path | None = None) -> dict[str, Any]:
    """Finished runs under ``runs_dir``; a variant whose run folder is gone (``outputs/`` is not
    versioned) keeps its entry from the ``previous`` results JSON, so collecting one new variant
    never drops the others."""
    old: dict[str, Any] = {}
    if previous is not None and previous.exists():
        old = json.loads(previous.read_text()).get("runs", {})
    runs: dict[str, Any] = {}
    for name in VARIANTS:
        path = runs_dir / name / "metrics.json"
        if path.exists():
            runs[name] = json.loads(path.read_text())
        elif name in old:
            runs[name] = old[name]
    return runs


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.{digits}f}"


def table(runs: dict[str, Any]) -> str:
    """Markdown: one row per variant × sampler × steps; spread per shape, translation, coverage."""
    head = (
        "| variant | sampler | steps | tet | cube | icosa | cone | cyl | mean spread ° | trans. err "
        "| coverage tet/cube/icosa | s/input |"
    )
    lines = [head, "|" + "---|" * 12]
    for name, res in runs.items():
        before = res.get("before")
        rows = []
        if before:
            rows.append(("untrained", str(before["num_steps"]), before))
        for sampler, by_steps in res.get("after", {}).items():
            for steps, r in by_steps.items():
                rows.append((sampler, steps, r))
        for sampler, steps, r in rows:
            shapes = r["shapes"]
            cov = "/".join(_fmt(shapes.get(s, {}).get("coverage"), 2) for s in DISCRETE)
            lines.append(
                f"| {name} | {sampler} | {steps} | "
                + " | ".join(
                    _fmt(shapes.get(s, {}).get("spread_deg")) for s in ("tet", "cube", "icosa", "cone", "cyl")
                )
                + f" | {_fmt(r['overall'].get('spread_deg'))} | {_fmt(r['overall'].get('translation_error'), 3)}"
                + f" | {cov} | {_fmt(r.get('seconds_per_input'), 3)} |"
            )
    return "\n".join(lines) + "\n"


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", choices=list(VARIANTS), help="run only these variants")
    ap.add_argument("--max-steps", type=int, default=None, help="override trainer.max_steps")
    ap.add_argument("--collect", action="store_true", help="only collect finished runs")
    args = ap.parse_args()
    extra = [f"trainer.max_steps={args.max_steps}"] if args.max_steps else []
    runs_dir, results = _names(args.max_steps)
    if not args.collect:
        for name in args.only or list(VARIANTS):
            run_variant(name, extra, runs_dir)
    runs = collect(runs_dir, previous=results)
    if not runs:
        print("no finished runs under", runs_dir, file=sys.stderr)
        return 1
    import torch

    doc = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "command": "python benchmarks/toy.py" + (f" --max-steps {args.max_steps}" if args.max_steps else ""),
        "machine": {"cpu": platform.processor() or platform.machine(), "threads": torch.get_num_threads()},
        "torch": torch.__version__,
        "variants": {k: VARIANTS[k] for k in runs},
        "runs": runs,
    }
    _atomic_write(results, json.dumps(doc, indent=1) + "\n")
    md = table(runs)
    _atomic_write(results.with_suffix(".md"), md)
    print(md)
    print(f"wrote {results.relative_to(ROOT)} and {results.with_suffix('.md').relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
