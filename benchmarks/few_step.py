"""Few network evaluations: samplers and distilled students at NFE 1 / 2 / 5 / 10 / 20 / 100 (issue 19).

    python benchmarks/few_step.py --model toy_so3=TEACHER.ckpt --student toy_so3=STUDENT.ckpt \\
        --model image=IMAGE.ckpt --student image=IMAGE_STUDENT.ckpt --num-samples 100

For each teacher checkpoint every sampler below runs at each NFE budget (the most steps whose network
evaluations fit: ``Sampler.steps_for_nfe``; the row states the NFE actually spent) on the teacher's
own test data; each student runs with its own sampler (few_step at the steps it was distilled for).
Per row: mean spread over the shapes (°), spread per shape, mode coverage of the discrete shapes
(share of the symmetry-equivalent poses with a hypothesis within 5°), translation error, seconds
per input. Rows are appended to the JSON as they finish (``--out``; the Markdown table next to it);
a run into an existing ``--out`` keeps the rows of the models it does not name (``commands`` lists
every run that wrote there).

Models named ``X`` and ``X_flow`` (or ``X_dsm``) are one family trained at the same budget (score
matching and flow matching, issue 30); the targets compare each with the family's best 100-NFE spread.
A flow model runs ``flow_euler`` (uniform times), ``flow_euler_cosine`` (cosine times),
``flow_euler_rot10`` (FrameFlow's rotation schedule, rate 10), ``flow_heun`` and
``flow_euler_renoise`` (predict the clean pose, re-draw the prior pose: ``few_step_renoise``'s analogue); its student
(``posediff distill method=reflow``) runs ``flow_euler`` at every budget.

Samplers of a score model: ``few_step`` (Euler step of the probability-flow ODE, posediff's deterministic few-step
sampler), ``few_step_renoise`` (predict clean, re-noise with fresh noise: the best at 100 in docs/sampling.md
steps), ``heun`` / ``heun_karras`` (order 2, schedule / Karras σ), ``crouch_grossman`` (order 3),
``rkmk`` (order 4).
"""

import argparse
import datetime as dt
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
NFES = (1, 2, 5, 10, 20, 100)
DISCRETE = ("tet", "cube", "icosa")


def samplers(diffusion: Any) -> dict[str, Any]:
    from posediff.diffusion import (
        CrouchGrossmanSampler,
        FewStepSampler,
        FlowEulerSampler,
        FlowHeunSampler,
        HeunSampler,
        RKMKSampler,
    )

    if diffusion.objective == "flow":  # a flow model's own samplers (posediff.diffusion.flow)
        return {
            "flow_euler": FlowEulerSampler(diffusion),
            "flow_euler_cosine": FlowEulerSampler(diffusion, spacing="cosine"),
            "flow_euler_rot10": FlowEulerSampler(
                diffusion, rotation_rate=10.0
            ),  # FrameFlow's rotation schedule
            "flow_heun": FlowHeunSampler(diffusion),
            "flow_euler_renoise": FlowEulerSampler(diffusion, fresh_prior=True),  # predict clean, fresh prior
        }
    return {
        "few_step": FewStepSampler(diffusion),
        "few_step_renoise": FewStepSampler(diffusion, renoise=1.0),
        "heun": HeunSampler(diffusion),
        "heun_karras": HeunSampler(diffusion, spacing="karras"),
        "crouch_grossman": CrouchGrossmanSampler(diffusion),
        "rkmk": RKMKSampler(diffusion),
    }


def _pairs(values: list[str], flag: str) -> dict[str, Path]:
    out = {}
    for v in values:
        name, sep, path = v.partition("=")
        if not sep:
            raise SystemExit(f"{flag} takes NAME=CKPT, got {v!r}")
        out[name] = Path(path)
    return out


def _row(model: str, kind: str, name: str, budget: int, nfe: int, steps: int, res: dict[str, Any]) -> dict:
    shapes = res["shapes"]
    cov = [shapes[s]["coverage"] for s in DISCRETE if s in shapes and shapes[s].get("coverage") is not None]
    return {
        "model": model,
        "kind": kind,
        "sampler": name,
        "nfe_budget": budget,
        "nfe": nfe,
        "steps": steps,
        "spread_deg": res["overall"]["spread_deg"],
        "spread_per_shape": {s: v["spread_deg"] for s, v in shapes.items()},
        "coverage": {s: shapes[s].get("coverage") for s in DISCRETE if s in shapes},
        "coverage_mean": sum(cov) / len(cov) if cov else None,
        "translation_error": res["overall"].get("translation_error"),
        "seconds_per_input": res["seconds_per_input"],
        "inputs": res["inputs"],
        "num_samples": res["num_samples"],
    }


def _data(module: Any) -> Any:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from posediff.config import register_resolvers

    register_resolvers()
    dm = instantiate(OmegaConf.create(module.config).data)
    dm.setup("test")
    return dm


def markdown(rows: list[dict[str, Any]], students: dict[str, dict]) -> str:
    lines = ["# Few-step sampling: spread (°) / coverage at each NFE", ""]
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        lines += [
            f"## {model}",
            "",
            "| sampler | NFE | steps | spread ° | "
            + " | ".join(f"{s} °" for s in mine[0]["spread_per_shape"])
            + " | coverage tet/cube/icosa | t err | s/input |",
        ]
        lines.append("|" + "---|" * (7 + len(mine[0]["spread_per_shape"])))
        for r in mine:
            cov = "/".join(
                "–" if r["coverage"].get(s) is None else f"{r['coverage'][s]:.2f}"
                for s in DISCRETE
                if s in r["coverage"]
            )
            t = "–" if r["translation_error"] is None else f"{r['translation_error']:.3f}"
            per = " | ".join(f"{v:.2f}" for v in r["spread_per_shape"].values())
            label = r["sampler"] if r["kind"] == "teacher" else f"**student** ({r['sampler']})"
            lines.append(
                f"| {label} | {r['nfe']} | {r['steps']} | {r['spread_deg']:.2f} | {per} | {cov or '–'} | {t} | {r['seconds_per_input']:.3f} |"
            )
        lines.append("")
        ref = [r for r in mine if r["kind"] == "teacher" and r["nfe_budget"] == 100]
        ode = [r for r in ref if r["sampler"] in ("heun", "flow_heun")]
        for r in [r for r in mine if r["nfe"] <= 5 and (r["kind"] == "student" or r["nfe"] == 5)]:
            if not ref:
                break
            best = min(ref, key=lambda q: q["spread_deg"])
            ratio = r["spread_deg"] / best["spread_deg"]
            text = (
                f"- {r['sampler']} ({r['kind']}) at {r['nfe']} NFE: {r['spread_deg']:.2f}° = {ratio:.2f}× the best "
                f"100-NFE spread ({best['sampler']}, {best['spread_deg']:.2f}°) — "
                f"{'within' if ratio <= 1.2 else 'not within'} 1.2×"
            )
            if ode:
                text += f"; {r['spread_deg'] / ode[0]['spread_deg']:.2f}× the teacher's ODE ({ode[0]['sampler']}, {ode[0]['nfe']} NFE, {ode[0]['spread_deg']:.2f}°)"
            text += (
                f"; coverage {_c(r)} (best 100-NFE: {_c(best)}{'' if not ode else ', ODE: ' + _c(ode[0])})"
            )
            lines.append(text)
        info = students.get(model)
        if info:
            how = (f"substeps {info.get('substeps')}" if info.get("method", "segment") == "segment"
                   else f"reflow, {info.get('rounds')} round(s), teacher {info.get('teacher_steps')} flow_heun steps")  # fmt: skip
            lines.append(
                f"- distillation: {info['updates']} updates, {info['seconds'] / 60:.1f} CPU minutes "
                f"({how}, {info['num_hypotheses']} hypotheses, reuse {info.get('reuse')})"
            )
        lines.append("")
    return "\n".join(lines) + "\n" + "\n" + targets(rows)


def family(model: str) -> str:
    """``toy_so3_flow`` and ``toy_so3_dsm`` (and ``toy_so3``) are one family: the same data and budget;
    so are variants named on, ``image_flow_r2`` (a second student of the same flow teacher)."""
    for tag in ("_flow", "_dsm"):
        head, sep, _ = model.partition(tag)
        if sep:
            return head
    return model


def targets(rows: list[dict[str, Any]]) -> str:
    """Issue 30's targets per family: at 5 NFE within 1.2× of the family's best 100-NFE spread with
    coverage no lower; at 1 NFE after straightening (a student) within 2×."""
    out = ["## Targets (issue 30)", "",
           "| model | best at 5 NFE | ×best-100 | coverage vs best-100's | 5-NFE target | best student at 1 NFE | × | 1-NFE target |",
           "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for fam in dict.fromkeys(family(r["model"]) for r in rows):
        mine = [r for r in rows if family(r["model"]) == fam]
        ref = [r for r in mine if r["kind"] == "teacher" and r["nfe_budget"] == 100]
        if not ref:
            continue
        best = min(ref, key=lambda q: q["spread_deg"])
        out.append(
            f"| **{fam}** family best at 100 NFE: {best['model']} {best['sampler']} | {best['spread_deg']:.2f}° | 1.00 | {_c(best)} | | | | |"
        )
        for model in dict.fromkeys(r["model"] for r in mine):
            five = [r for r in mine if r["model"] == model and r["nfe"] <= 5 and r["nfe_budget"] == 5]
            one = [r for r in mine if r["model"] == model and r["kind"] == "student" and r["nfe"] == 1]
            cells = [model]
            if five:
                f = min(five, key=lambda q: q["spread_deg"])
                ratio = f["spread_deg"] / best["spread_deg"]
                cov_ok = (
                    f["coverage_mean"] is None
                    or best["coverage_mean"] is None
                    or f["coverage_mean"] >= best["coverage_mean"]
                )
                cells += [f"{f['sampler']} {f['spread_deg']:.2f}°", f"{ratio:.2f}", f"{_c(f)} vs {_c(best)}",
                          "**met**" if ratio <= 1.2 and cov_ok else "not met"]  # fmt: skip
            else:
                cells += ["", "", "", ""]
            if one:
                o = min(one, key=lambda q: q["spread_deg"])
                r1 = o["spread_deg"] / best["spread_deg"]
                cells += [f"{o['spread_deg']:.2f}°", f"{r1:.2f}", "**met**" if r1 <= 2.0 else "not met"]
            else:
                cells += ["", "", ""]
            out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def compact(rows: list[dict[str, Any]]) -> str:
    """One table per model (docs/sampling.md): spread ° (mean coverage of tet/cube/icosa) per sampler and NFE budget
    (the NFE a row actually spent is at most its budget)."""
    out = []
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        names = list(dict.fromkeys(r["sampler"] for r in mine if r["kind"] == "teacher"))
        budgets = sorted({r["nfe_budget"] for r in mine})
        out += [f"**{model}** — spread ° (coverage)", "", "| NFE ≤ | " + " | ".join(names) + " | student |",
                "|" + "---|" * (len(names) + 2)]  # fmt: skip
        for b in budgets:
            cells = []
            for n in [*names, None]:
                hit = [
                    r
                    for r in mine
                    if r["nfe_budget"] == b and (r["sampler"] == n if n else r["kind"] == "student")
                ]
                if not hit and n is not None:  # the budget's row was a duplicate of a smaller budget's
                    hit = [
                        max((r for r in mine if r["sampler"] == n and r["nfe"] <= b), key=lambda r: r["nfe"])
                    ]
                cells.append(f"{hit[0]['spread_deg']:.1f} ({_c(hit[0])})" if hit else "")
            out.append(f"| {b} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def _c(row: dict[str, Any]) -> str:
    return "–" if row["coverage_mean"] is None else f"{row['coverage_mean']:.3f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", default=[], help="NAME=TEACHER.ckpt (repeatable)")
    ap.add_argument("--student", action="append", default=[], help="NAME=STUDENT.ckpt of that teacher")
    ap.add_argument("--nfe", type=int, nargs="+", default=list(NFES))
    ap.add_argument("--samplers", nargs="+", default=None, help="a subset of the sampler names")
    ap.add_argument("--num-samples", type=int, default=100)
    ap.add_argument("--max-inputs", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--readme", type=Path, nargs="+", default=None, help="print the compact tables of these JSONs"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "few_step.json")
    args = ap.parse_args()
    if args.readme:
        print("\n".join(compact(json.loads(p.read_text())["rows"]) for p in args.readme))
        return 0

    from posediff import load_checkpoint
    from posediff._io import atomic_write_json, atomic_write_text
    from posediff.evaluation import evaluate_data

    teachers, studs = _pairs(args.model, "--model"), _pairs(args.student, "--student")
    previous = json.loads(args.out.read_text()) if args.out.is_file() else {}
    rows = [r for r in previous.get("rows", []) if r["model"] not in teachers]
    students = {k: v for k, v in previous.get("students", {}).items() if k not in teachers}
    command = " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
    earlier = previous.get("commands", [previous["command"]] if "command" in previous else [])
    result = {
        "command": command,
        "commands": [*earlier, command],  # every run that wrote into this file, in order
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "threads": torch.get_num_threads()},
        "checkpoints": {**previous.get("checkpoints", {}), **{k: str(v) for k, v in teachers.items()},
                        **{f"{k} (student)": str(v) for k, v in studs.items()}},
        "rows": rows,
        "students": students,
    }  # fmt: skip

    def save() -> None:
        atomic_write_json(args.out, result)
        atomic_write_text(args.out.with_suffix(".md"), markdown(result["rows"], result["students"]))

    for model, path in teachers.items():
        teacher = load_checkpoint(path)
        dm = _data(teacher)
        kw = {"num_samples": args.num_samples, "seed": args.seed, "max_inputs": args.max_inputs}
        table = samplers(teacher.diffusion)
        names = args.samplers or list(table)
        for name in names:
            s = table[name]
            seen = set()
            for budget in args.nfe:
                steps = s.steps_for_nfe(budget)
                nfe = s.network_calls(steps)
                if nfe in seen or nfe > budget:
                    continue
                seen.add(nfe)
                t = time.perf_counter()
                res = evaluate_data(teacher, dm, num_steps=steps, sampler=s, **kw)
                result["rows"].append(_row(model, "teacher", name, budget, nfe, steps, res))
                print(f"{model} {name} NFE {nfe} ({steps} steps): {res['overall']['spread_deg']:.2f}° "
                      f"[{time.perf_counter() - t:.0f} s]", flush=True)  # fmt: skip
                save()
        if model in studs:
            student = load_checkpoint(studs[model])
            info = dict(student.config.get("distill", {}))
            result["students"][model] = info
            own = type(student.sampler)(student.diffusion)
            label = f"{info.get('method', 'segment')} student ({own.name})"
            budgets = (
                args.nfe
                if student.diffusion.objective == "flow"
                else [own.network_calls(int(student.sampler.num_steps))]
            )
            seen = set()
            for budget in budgets:
                steps = own.steps_for_nfe(budget)
                nfe = own.network_calls(steps)
                if nfe in seen or nfe > budget:
                    continue
                seen.add(nfe)
                res = evaluate_data(student, dm, num_steps=steps, sampler=own, **kw)
                result["rows"].append(_row(model, "student", label, budget, nfe, steps, res))
                print(f"{model} {label} NFE {nfe}: {res['overall']['spread_deg']:.2f}°", flush=True)
                save()
    save()
    print(markdown(result["rows"], result["students"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
