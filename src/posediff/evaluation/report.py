"""Tables of evaluation results: one run (per shape) and a sweep (the paper's Table 4 layout).

``posediff eval`` writes ``metrics.json`` (the dict :func:`posediff.evaluation.evaluate` returns, plus
the run's settings) and ``metrics.md`` (:func:`run_table`). A Hydra multirun over
``sampler.num_steps`` (or anything else) leaves one such folder per job; :func:`collect_sweep`
gathers them into one table — steps, seconds per image, images per second, then the metrics —
written as ``report.md`` / ``report.json`` next to the jobs. :class:`ReportCallback` does this at
the end of every ``posediff eval -m`` multirun; ``posediff report dir=<sweep>`` does it afterwards.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from .._io import atomic_write_json, atomic_write_text

#: (metric key, column header) in table order; absent keys are skipped. BOP evaluations
#: (:mod:`posediff.evaluation.bop`) fill the paper's Table 3 columns: MSPD, MSSD, VSD (BOP19 average
#: recalls), R@2/5/10°, T@2/5/10 cm; their per-axis recalls go to :func:`axis_table`.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("AR_MSPD", "MSPD"),
    ("AR_MSSD", "MSSD"),
    ("AR_VSD", "VSD"),
    ("AR", "AR"),
    ("spread_deg", "spread (°)"),
    ("recall_rot@2", "R@2°"),
    ("recall_rot@5", "R@5°"),
    ("recall_rot@10", "R@10°"),
    ("translation_error", "t err"),
    ("recall_trans@0.02", "T@0.02"),
    ("recall_trans@0.05", "T@0.05"),
    ("recall_trans@0.1", "T@0.1"),
    ("recall_trans@2cm", "T@2cm"),
    ("recall_trans@5cm", "T@5cm"),
    ("recall_trans@10cm", "T@10cm"),
    ("coverage", "coverage"),
    ("log_likelihood", "log-lik."),
    ("log_likelihood_joint", "joint log-lik."),
    ("log_likelihood_ode_error", "± ODE"),
)
#: the paper's per-axis translation recalls (its supplement, "Translation Analysis on T-LESS")
AXIS_COLUMNS: tuple[tuple[str, str], ...] = tuple(
    (f"recall_{a}@{c}cm", f"{a}@{c}cm") for a in "xyz" for c in (2, 5, 10)
)


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _columns(rows: Sequence[dict[str, Any]]) -> list[tuple[str, str]]:
    return [(k, h) for k, h in COLUMNS if any(k in r for r in rows)]


def run_table(result: dict[str, Any]) -> str:
    """Markdown: one row per shape (object) and an ``overall`` row of one evaluation (mean over shapes;
    for BOP, recall over all targets), and for BOP the per-axis table."""
    rows = [*result["shapes"].items(), ("overall", result["overall"])]
    if "object_mean" in result:  # BOP: the paper's per-object average next to the pooled recall
        rows.insert(-1, ("mean of objects", result["object_mean"]))
    cols = _columns([m for _, m in rows])
    header = ["object" if result.get("kind") == "bop" else "shape", *(h for _, h in cols)]
    body = [[shape, *(_fmt(m.get(k)) for k, _ in cols)] for shape, m in rows]
    steps = result.get("num_steps")
    if "csv" in result:  # posediff score: a results file, no sampler
        title = (
            f"{result['csv']}: {result.get('estimates_scored', 0) + result.get('estimates_ignored', 0)} "
            f"estimates, {result.get('estimates_scored')} scored ({result.get('estimates_ignored')} ignored: "
            f"beyond a target's inst_count, or of an object that is no target of its image); "
            f"{result.get('seconds', math.nan):.2f} s\n\n"
        )
        missing = f"{result.get('without_estimate')} in an image and object without any estimate"
    else:
        title = (
            f"{result.get('sampler', 'sampler')}, {steps} steps, {result.get('num_samples')} hypotheses per "
            f"input, {result.get('inputs', '?')} inputs; {result.get('seconds_per_input', math.nan):.3f} s per input\n\n"
        )
        missing = f"{result.get('skipped')} without an estimate (too few visible pixels)"
        ll = result.get("log_likelihood")
        if ll:
            title += (
                f"{'joint ' if ll['key'] == 'log_likelihood_joint' else ''}log-likelihood of the ground truth: "
                f"probability-flow ODE on {ll['steps']} levels (± ODE: the mean difference to {ll['check_steps']}), "
                f"{ll['seconds_per_input']:.3f} s per input; density w.r.t. the {ll['measure']}\n\n"
            )
    if result.get("kind") != "bop":
        return title + _markdown(header, body)
    note = (
        f"BOP19 protocol: {result.get('targets')} targets, {missing}: misses"
        f"{'' if result.get('vsd', True) else '; VSD not computed'}; per image and object the top "
        "inst_count estimates by score, matched greedily to any of its instances (the BOP toolkit's "
        "matching); recalls in [0, 1]; overall = over all targets (the BOP toolkit), mean of objects = the "
        "paper's per-object average\n\n"
    )
    return title + note + _markdown(header, body) + "\nper-axis translation recall\n\n" + axis_table(result)


def axis_table(result: dict[str, Any]) -> str:
    """Markdown: the per-axis translation recalls x/y/z@2/5/10 cm per object and overall."""
    rows = [*result["shapes"].items(), ("overall", result["overall"])]
    if "object_mean" in result:
        rows.insert(-1, ("mean of objects", result["object_mean"]))
    cols = [(k, h) for k, h in AXIS_COLUMNS if any(k in m for _, m in rows)]
    return _markdown(
        ["object", *(h for _, h in cols)], [[s, *(_fmt(m.get(k)) for k, _ in cols)] for s, m in rows]
    )


def sweep_rows(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One flat row per evaluation (sorted by sampler, then steps): the Table 4 columns."""
    rows = []
    for r in results:
        sec = float(r.get("seconds_per_input", math.nan))
        rows.append(
            {
                "sampler": r.get("sampler"),
                "steps": r.get("num_steps"),
                "seconds_per_image": sec,
                "fps": 1.0 / sec if sec > 0 else math.nan,
                **{k: v for k, v in r["overall"].items()},
                "dir": r.get("dir"),
            }
        )
    return sorted(rows, key=lambda x: (str(x["sampler"]), x["steps"] if x["steps"] is not None else -1))


def sweep_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown in the paper's Table 4 layout (means over shapes)."""
    cols = _columns(rows)
    header = ["sampler", "steps", "s / image", "FPS", *(h for _, h in cols)]
    body = [
        [
            str(r["sampler"]),
            str(r["steps"]),
            _fmt(r["seconds_per_image"], 4),
            _fmt(r["fps"], 2),
            *(_fmt(r.get(k)) for k, _ in cols),
        ]
        for r in rows
    ]
    return _markdown(header, body)


def collect_sweep(
    sweep_dir: str | os.PathLike[str], *, write: bool = True
) -> tuple[list[dict[str, Any]], str]:
    """Read every ``*/metrics.json`` under ``sweep_dir`` (one level, or the folder itself) and build
    the sweep table; with ``write``, save ``report.md`` and ``report.json`` in ``sweep_dir``."""
    root = Path(sweep_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"no folder {root} (give the multirun folder of posediff eval -m ...)")
    files = sorted(root.glob("*/metrics.json")) or sorted(root.glob("metrics.json"))
    failed = failed_jobs(root)
    if not files and failed:
        raise FileNotFoundError(f"every job under {root} failed: " + "; ".join(failed))
    if not files:
        raise FileNotFoundError(f"no */metrics.json under {root} (is it a posediff eval output folder?)")
    results = []
    for f in files:
        r = json.loads(f.read_text())
        if "overall" not in r:
            continue  # e.g. a fit summary
        r["dir"] = str(f.parent.relative_to(root)) if f.parent != root else "."
        results.append(r)
    if not results:
        raise FileNotFoundError(f"no evaluation results (metrics.json with 'overall') under {root}")
    rows = sweep_rows(results)
    table = sweep_table(rows)
    if failed:
        table += f"\n\n{len(failed)} failed job(s), not in the table:\n" + "\n".join(f"- {f}" for f in failed)
    if write:
        ckpt = results[0].get("ckpt_path", "?")
        n = results[0].get("num_samples", "?")
        atomic_write_text(
            root / "report.md",
            f"# posediff eval sweep\n\ncheckpoint: `{ckpt}`; {n} hypotheses per image; "
            "metrics are means over shapes (per-shape tables in each job's metrics.md)\n\n" + table,
        )
        atomic_write_json(root / "report.json", rows)
    return rows, table


def failed_jobs(sweep_dir: str | os.PathLike[str]) -> list[str]:
    """``job <n> (<overrides>): <message>`` for every job of a sweep that left ``failed.json``
    (written by ``posediff.cli`` when a job exits non-zero), or whose folder has no ``metrics.json``."""
    root = Path(sweep_dir)
    out = []
    for job in sorted(
        (d for d in root.iterdir() if d.is_dir() and (d / ".hydra").is_dir()), key=lambda d: d.name
    ):
        if (job / "metrics.json").is_file():
            continue
        try:
            info = json.loads((job / "failed.json").read_text())
            out.append(f"job {job.name} ({' '.join(info.get('overrides', []))}): {info.get('message')}")
        except (OSError, ValueError):
            out.append(f"job {job.name}: no metrics.json (it failed or was interrupted)")
    return out


class ReportCallback(Callback):
    """Hydra callback: after a multirun, collect the jobs' ``metrics.json`` into ``report.md``."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        try:
            _, table = collect_sweep(sweep_dir)
        except FileNotFoundError as e:
            print(f"posediff eval: no sweep report ({e})")
            return
        print(table)
        print(f"report: {sweep_dir / 'report.md'}")


def headline(result: dict[str, Any]) -> str:
    """The one number of an evaluation: the spread (SYMSOL, toy) or the BOP19 average recall."""
    o, nan = result.get("overall", {}), float("nan")
    if result.get("kind") == "bop":
        return f"BOP19 AR {o.get('AR', nan):.3f} over {result.get('targets')} targets"
    return f"spread {o.get('spread_deg', nan):.2f}°"


def fit_markdown(results: dict[str, Any]) -> str:
    """The before/after evaluations as markdown: a before → after spread line per shape, then the
    full per-shape tables."""
    parts = [f"# posediff fit: {results.get('experiment', 'none')}\n"]
    train = results.get("train", {})
    if train:
        parts.append(
            f"trained {train['steps']} steps in {train['seconds']:.0f} s; "
            f"loss {train['loss_first']:.3f} → {train['loss_last']:.3f} (mean of the first / last 50 steps)\n"
        )
    after = [(name, steps, res) for name, by in results.get("after", {}).items() for steps, res in by.items()]
    if "before" in results and after:
        b, (name, steps, a) = results["before"], after[-1]
        if a.get("kind") == "bop":
            cols = [("AR", "AR"), ("recall_rot@5", "R@5°"), ("recall_trans@5cm", "T@5cm")]
        else:
            cols = [("spread_deg", "spread (°)"), ("translation_error", "t err")]
        cols = [(k, h) for k, h in cols if k in a["overall"]]
        head = "| shape |" + "".join(f" {h} before | {h} after |" for _, h in cols)
        lines = [head, "|---|" + "---|---|" * len(cols)]
        nan = float("nan")
        for shape in [*a["shapes"], "overall"]:
            mb = b["overall"] if shape == "overall" else b["shapes"].get(shape, {})
            ma = a["overall"] if shape == "overall" else a["shapes"][shape]
            row = f"| {shape} |"
            for k, _ in cols:
                digits = 1 if k == "spread_deg" else 3
                row += f" {mb.get(k, nan):.{digits}f} | {ma.get(k, nan):.{digits}f} |"
            lines.append(row)
        parts.append(f"untrained vs trained ({name}, {steps} steps):\n\n" + "\n".join(lines) + "\n")
    if "before" in results:
        parts.append("## untrained model\n\n" + run_table(results["before"]))
    for name, steps, res in after:
        parts.append(f"## trained model — sampler {name}, {steps} steps\n\n" + run_table(res))
    return "\n".join(parts)


__all__ = [
    "failed_jobs",
    "fit_markdown",
    "headline",
    "AXIS_COLUMNS",
    "COLUMNS",
    "ReportCallback",
    "axis_table",
    "collect_sweep",
    "run_table",
    "sweep_rows",
    "sweep_table",
]
