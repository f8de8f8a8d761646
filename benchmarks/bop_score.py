"""``posediff score`` against the official BOP toolkit: the same BOP19 scores? how long does each take?

    python benchmarks/bop_score.py                       # posediff only (fixture + T-LESS-sized list)
    python benchmarks/bop_score.py --quick --out /tmp/bop_score.json        # smoke run, small only
    python benchmarks/bop_score.py --toolkit RUN.sh --toolkit-prepare PREPARE.py   # both

Datasets, made with posediff's BOP fixture at T-LESS's image size (720×540, the T-LESS primesense
camera) in ``--workdir``:

* ``fixture``: 2 test scenes × 3 images × 6 instances (≈ 35 targets, siblings in every image);
* ``tless_sized``: 20 scenes × 50 images × 7 instances — 1000 test images and about 6 500 targets,
  the size of T-LESS's BOP19 test set (1000 images, 6 423 targets). Only its test split is made.

Results files (BOP19 CSV, one per case): ``truth`` (the ground truth of every target instance),
``siblings`` (each instance's estimate is another instance's pose, within an image and object),
``duplicates`` (every estimate of an image and object is its first instance's pose), ``shifted``
(x shifted by 0–100 mm), ``noisy3`` (three estimates per target, turned up to 40° and shifted
~15 mm, random scores: the top-``inst_count`` choice and the matching both matter) and, on the
T-LESS-sized list, ``noisy1`` (one perturbed estimate per target).

posediff is timed in-process from reading the CSV to the scores (reading the targets, the checks,
MSSD, MSPD, VSD and the paper's recalls; imports and the dataset's creation excluded). The toolkit
is timed around its ``scripts/eval_bop19_pose.py`` (errors, then 120 score subprocesses), through
two commands of a local toolkit setup that are not part of posediff (the toolkit is not on PyPI):
``--toolkit RUN.sh`` runs ``RUN.sh DATASET_PARENT CSV OUT_DIR`` and prints the toolkit's
``scores_bop19.json`` then ``toolkit_seconds N``; ``--toolkit-prepare PREPARE.py`` runs
``python PREPARE.py SRC DST/tless`` to give the dataset the 30 T-LESS object ids the toolkit's
``dataset_params.py`` expects (the extra ids never occur in the ground truth). Results: a table on
stdout and ``benchmarks/results/bop_score.json``, written after every case.
"""

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from posediff._io import atomic_write_json  # noqa: E402
from posediff.data.bop import BopDataModule  # noqa: E402
from posediff.data.bop.fixture import make_bop_fixture  # noqa: E402
from posediff.evaluation import check_estimates, score_estimates  # noqa: E402
from posediff.metrics.bop19 import read_bop19_csv, write_bop19_csv  # noqa: E402

DATASETS = {
    "fixture": {"test_scenes": 2, "test_images": 3, "test_instances": 6},
    "tless_sized": {"test_scenes": 20, "test_images": 50, "test_instances": 7},
}
KEYS = (("AR_VSD", "bop19_average_recall_vsd"), ("AR_MSSD", "bop19_average_recall_mssd"),
        ("AR_MSPD", "bop19_average_recall_mspd"), ("AR", "bop19_average_recall"))  # fmt: skip


def _dataset(workdir: Path, name: str) -> Path:
    out = workdir / name / "tless"  # the toolkit knows the dataset by its folder name
    if not (out / "test_targets_bop19.json").exists():
        sizes = DATASETS[name]
        extra = {"pbr_scenes": 0, "train_views": 0} if name == "tless_sized" else {}
        t0 = time.perf_counter()
        s = make_bop_fixture(out, seed=0, width=720, height=540, **sizes, **extra, overwrite=out.exists())
        print(f"made {name}: {s.line()} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def _rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.uniform(0.0, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _rows(dm: BopDataModule, case: str, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    groups: dict[tuple, list] = {}
    for inst in dm.targets:
        groups.setdefault((inst.scene_id, inst.im_id, inst.obj_id), []).append(inst)
    rows = []

    def add(inst, R, t, score=1.0):  # noqa: ANN001, ANN202
        rows.append({"scene_id": inst.scene_id, "im_id": inst.im_id, "obj_id": inst.obj_id, "score": float(score),
                     "R": np.asarray(R), "t": np.asarray(t), "time": 0.25})  # fmt: skip

    for g in groups.values():
        for k, inst in enumerate(g):
            if case == "truth":
                add(inst, inst.R, inst.t)
            elif case == "siblings":
                other = g[(k + 1) % len(g)]
                add(inst, other.R, other.t)
            elif case == "duplicates":
                add(inst, g[0].R, g[0].t)
            elif case == "shifted":
                add(inst, inst.R, inst.t + [(0, 5, 12, 30, 60, 100)[len(rows) % 6], 0.0, 0.0])
            elif case in ("noisy3", "noisy1"):
                for _ in range(3 if case == "noisy3" else 1):
                    add(inst, _rotation(rng, 40.0 if case == "noisy3" else 20.0) @ inst.R,
                        inst.t + rng.normal(scale=15.0 if case == "noisy3" else 10.0, size=3), rng.uniform())  # fmt: skip
    return rows


def _posediff(root: Path, csv: Path) -> tuple[dict, float]:
    dm = BopDataModule(str(root), num_workers=0, augment=None)
    t0 = time.perf_counter()
    rows = read_bop19_csv(csv)
    dm.read_targets()
    check_estimates(rows, dm)
    res = score_estimates(dm, rows)
    return res, time.perf_counter() - t0


def _toolkit(args: argparse.Namespace, root: Path, csv: Path, workdir: Path) -> tuple[dict, float] | None:
    if not args.toolkit:
        return None
    parent = workdir / "toolkit" / root.parent.name
    if not (parent / "tless" / "test_targets_bop19.json").exists():
        subprocess.run([sys.executable, args.toolkit_prepare, str(root), str(parent / "tless")], check=True)
    out = subprocess.run([args.toolkit, str(parent), str(csv), str(workdir / "toolkit_eval")],
                         capture_output=True, text=True)  # fmt: skip
    if out.returncode != 0:
        print(out.stderr[-2000:], file=sys.stderr)
        return None
    lines = out.stdout.strip().splitlines()
    seconds = float(lines[-1].split()[-1])
    scores = json.loads("\n".join(lines[lines.index("{") : lines.index("}") + 1]))
    return scores, seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", default=str(ROOT / "benchmarks" / ".work" / "bop_score"))
    ap.add_argument("--toolkit", default=None, help="RUN.sh DATASET_PARENT CSV OUT_DIR (module docstring)")
    ap.add_argument("--toolkit-prepare", default=None, help="PREPARE.py SRC DST/tless (module docstring)")
    ap.add_argument("--quick", action="store_true", help="the small fixture and two cases only")
    ap.add_argument(
        "--skip-tless-toolkit", action="store_true", help="no toolkit run on the T-LESS-sized list"
    )
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bop_score.json"))
    args = ap.parse_args()
    if bool(args.toolkit) != bool(args.toolkit_prepare):
        ap.error("--toolkit and --toolkit-prepare go together")
    workdir = Path(args.workdir)
    plan = [("fixture", c) for c in ("truth", "siblings", "duplicates", "shifted", "noisy3")]
    plan += [("tless_sized", "noisy1")]
    if args.quick:
        plan = [("fixture", "truth"), ("fixture", "siblings")]
    result = {
        "benchmark": "bop_score",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "rows": [],
    }
    print(f"{'dataset':<12} {'case':<11} {'targets':>7} {'rows':>6} {'posediff s':>10} {'toolkit s':>9}  "
          f"AR (posediff / toolkit): VSD, MSSD, MSPD, AR")  # fmt: skip
    for name, case in plan:
        root = _dataset(workdir, name)
        dm = BopDataModule(str(root), num_workers=0, augment=None)
        dm.read_targets()
        csv = workdir / "csv" / name / f"{case}_tless-test.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        write_bop19_csv(csv, _rows(dm, case))
        res, seconds = _posediff(root, csv)
        row = {"dataset": name, "case": case, "targets": res["targets"],
               "images": len({i.key[:2] for i in dm.targets}),
               "estimates": res["estimates_scored"] + res["estimates_ignored"], "posediff_seconds": seconds,
               "posediff": {k: res["overall"][k] for k, _ in KEYS}}  # fmt: skip
        skip = name == "tless_sized" and args.skip_tless_toolkit
        tk = None if skip else _toolkit(args, root, csv, workdir)
        if tk is not None:
            scores, row["toolkit_seconds"] = tk
            row["toolkit"] = {k: float(scores[t]) for k, t in KEYS}
            row["max_abs_difference"] = max(abs(row["posediff"][k] - row["toolkit"][k]) for k, _ in KEYS)
            row["speed_up"] = row["toolkit_seconds"] / seconds
        result["rows"].append(row)
        atomic_write_json(args.out, result)
        ars = ", ".join(
            f"{row['posediff'][k]:.4f}" + (f" / {row['toolkit'][k]:.4f}" if "toolkit" in row else "")
            for k, _ in KEYS
        )
        print(f"{name:<12} {case:<11} {row['targets']:>7} {row['estimates']:>6} {seconds:>10.2f} "
              f"{row.get('toolkit_seconds', float('nan')):>9.1f}  {ars}", flush=True)  # fmt: skip
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
