"""What the in-process BOP evaluation costs per target on the CPU, at T-LESS's image size.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/bop_eval.py
    python benchmarks/bop_eval.py --quick --out /tmp/bop_eval.json     # smoke run

Setting: a 720×540 image with the T-LESS primesense camera, objects 500–800 mm away, an evaluation
model of ``--points`` vertices (the fixture's box and cylinder, subdivided), estimates a few degrees
and millimetres off the truth. Timed per target (medians over ``--repeats`` rounds of ``--targets``):

* **MSSD** and **MSPD** over the object's BOP symmetry set (box: 4 members; cylinder with a continuous
  symmetry and a flip: 630 at ``max_sym_disc_step`` 0.01);
* **VSD** — two depth renders (``BopRenderer.render_depth``, Mesa's software EGL) plus the error at the
  ten τ;
* **recalls** — the paper's R@ / T@ / x/y/z@ for all targets at once, per target.

The sum is what ``posediff eval`` adds to sampling for each BOP19 target (T-LESS has 6 423 targets in
its BOP19 test set). Results: a table on stdout and ``benchmarks/results/bop_eval.json``.
"""

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from posediff._io import atomic_write_json  # noqa: E402
from posediff.data.bop.fixture import TLESS_PRIMESENSE, make_model, model_info  # noqa: E402
from posediff.data.bop.render import BopRenderer  # noqa: E402
from posediff.metrics import bop, bop19  # noqa: E402


def _mesh(obj_id: int, points: int):  # noqa: ANN202
    mesh = make_model(obj_id)
    while len(mesh.vertices) < points:
        mesh = mesh.subdivide()
    return mesh


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _poses(rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, ...]]:
    out = []
    for _ in range(n):
        R = _rot(rng.normal(size=3), rng.uniform(0, np.pi))
        t = np.array([rng.uniform(-80, 80), rng.uniform(-60, 60), rng.uniform(500, 800)])
        R_e = _rot(rng.normal(size=3), np.radians(rng.uniform(1, 8))) @ R
        t_e = t + rng.normal(scale=5.0, size=3)
        out.append((R_e, t_e, R, t))
    return out


def _median_ms(fn, n: int, repeats: int) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0 / n)
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--quick", action="store_true", help="5 targets, 1 round, 1000 points")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bop_eval.json"))
    args = ap.parse_args()
    if args.quick:
        args.targets, args.repeats, args.points = 5, 1, 1000
    cam = TLESS_PRIMESENSE
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    W, H = int(cam["width"]), int(cam["height"])
    renderer = BopRenderer(W, H)
    rng = np.random.default_rng(0)
    rows = []
    for obj_id, name in ((2, "box"), (1, "cylinder")):
        mesh = _mesh(obj_id, args.points)
        info = model_info(obj_id, mesh)
        syms = bop.symmetry_transforms(info)
        pts = np.asarray(mesh.vertices, dtype=np.float64)
        renderer.add_model(obj_id, mesh)
        poses = _poses(rng, args.targets)
        tests = [renderer.render_depth(obj_id, R, t, K) for _, _, R, t in poses]  # the "test" depth images
        d = info["diameter"]

        def run_mssd() -> None:
            for R_e, t_e, R, t in poses:  # noqa: B023
                bop.mssd(R_e, t_e, R, t, pts, syms, diameter=d)  # noqa: B023

        def run_mspd() -> None:
            for R_e, t_e, R, t in poses:  # noqa: B023
                bop.mspd(R_e, t_e, R, t, K, pts, syms)  # noqa: B023

        def run_vsd() -> None:
            for (R_e, t_e, R, t), test in zip(poses, tests, strict=True):  # noqa: B023
                est, gt = renderer.render_depth(obj_id, R_e, t_e, K), renderer.render_depth(obj_id, R, t, K)  # noqa: B023
                bop.vsd(est, gt, test, K, 15.0, bop19.BOP19.vsd_taus, d)  # noqa: B023

        def run_recalls() -> None:
            Re, te, Rg, tg = (np.stack(x) for x in zip(*poses, strict=True))  # noqa: B023
            bop19.pose_recalls(Re, te, Rg, tg, syms)  # noqa: B023

        row = {
            "object": name,
            "symmetries": len(syms[0]),
            "points": len(pts),
            "mssd_ms": _median_ms(run_mssd, args.targets, args.repeats),
            "mspd_ms": _median_ms(run_mspd, args.targets, args.repeats),
            "vsd_ms": _median_ms(run_vsd, args.targets, args.repeats),
            "recalls_ms": _median_ms(run_recalls, args.targets, args.repeats),
        }
        row["total_ms"] = row["mssd_ms"] + row["mspd_ms"] + row["vsd_ms"] + row["recalls_ms"]
        rows.append(row)
    renderer.close()
    head = f"{'object':<9} {'syms':>5} {'points':>7} {'MSSD':>8} {'MSPD':>8} {'VSD':>8} {'recalls':>8} {'total':>8}  (ms per target)"
    print(head)
    for r in rows:
        print(f"{r['object']:<9} {r['symmetries']:>5} {r['points']:>7} {r['mssd_ms']:>8.2f} {r['mspd_ms']:>8.2f} "
              f"{r['vsd_ms']:>8.2f} {r['recalls_ms']:>8.3f} {r['total_ms']:>8.2f}")  # fmt: skip
    result = {
        "benchmark": "bop_eval",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "settings": {
            "image": [W, H],
            "targets": args.targets,
            "repeats": args.repeats,
            "points": args.points,
        },
        "rows": rows,
    }
    atomic_write_json(args.out, result)
    print(f"results: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
