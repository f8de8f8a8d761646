"""Throughput of batched Lie group ops: posediff next to kornia, pytorch-kinematics, roma, pypose.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/lie_ops.py            # N = 10⁶, float32, 2 threads
    python benchmarks/lie_ops.py --n 100000 --repeats 5 --no-compiled  # a quick look
    OMP_WAIT_POLICY=PASSIVE python benchmarks/lie_ops.py --tuned-malloc  # glibc keeps big blocks

Every implementation is timed on the same inputs in the same run, interleaved round by round, and
the median is reported as millions of elements per second (Melem/s). Peers are timed in their own
native element type (kornia/pypose/roma keep quaternions; posediff keeps matrices), with inputs
converted before timing starts. ``posediff`` is the eager kernel, ``posediff[compiled]`` the
same kernel through ``torch.compile`` (``LieGroup(compiled=True)``; its compile time is reported
apart and not counted). Results: a table on stdout and ``benchmarks/results/lie_ops.json``.

At N = 10⁶ a posediff output is 36 MB (SO3) or 64 MB (SE3) of fresh memory; glibc hands blocks
above 32 MB out by ``mmap`` and every call then pays ~2 µs per 4 KiB page in page faults (~24 ms
for 64 MB), which peers with 4- or 7-float quaternion outputs avoid. ``--tuned-malloc`` re-runs
the whole comparison (every library alike) with glibc told to keep such blocks on the heap
(``MALLOC_MMAP_THRESHOLD_``/``MALLOC_TRIM_THRESHOLD_``, the effect jemalloc/tcmalloc have, as
PyTorch's CPU tuning guide recommends) and writes ``lie_ops_tuned_malloc.json``.
"""

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from posediff._io import atomic_write_json
from posediff.lie import R3SO3, SE3, SO3

warnings.filterwarnings("ignore")
RESULTS = Path(__file__).resolve().parent / "results" / "lie_ops.json"
TUNED = RESULTS.with_name("lie_ops_tuned_malloc.json")
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(1 << 40), "MALLOC_TRIM_THRESHOLD_": str(1 << 40)}
GOAL = 1.5


def _peers_available() -> dict[str, Any]:
    mods: dict[str, Any] = {}
    for name in ("kornia", "pytorch_kinematics", "roma", "pypose"):
        try:
            mods[name] = __import__(name)
        except Exception as e:  # noqa: BLE001 - a missing/broken peer is reported, not fatal
            print(f"peer {name} unavailable: {type(e).__name__}: {e}", file=sys.stderr)
    return mods


def build_cases(
    n: int, compiled: bool, peers: dict[str, Any]
) -> dict[tuple[str, str], dict[str, Callable[[], Any]]]:
    """(group, op) → {implementation: zero-argument callable}, inputs prepared beforehand."""
    gen = torch.Generator().manual_seed(0)
    f32 = torch.float32
    phi = torch.randn(n, 3, generator=gen)
    phi = phi / phi.norm(dim=-1, keepdim=True) * (torch.rand(n, 1, generator=gen) * 3.1)
    rho = torch.randn(n, 3, generator=gen)
    xi = torch.cat([rho, phi], dim=-1)
    so3, se3, r3so3 = SO3(), SE3(), R3SO3()
    R1, R2 = so3.exp(phi), so3.exp(phi.flip(0))
    T1, T2 = se3.exp(xi), se3.exp(xi.flip(0))
    P1, P2 = r3so3.exp(xi), r3so3.exp(xi.flip(0))

    cases: dict[tuple[str, str], dict[str, Callable[[], Any]]] = {}

    def ours(group_name: str, group_cls: type, op: str, *args: torch.Tensor) -> None:
        impls = cases.setdefault((group_name, op), {})
        impls["posediff"] = lambda: getattr(group_cls(), op)(*args)
        if compiled:
            fused = group_cls(compiled=True)
            impls["posediff[compiled]"] = lambda: getattr(fused, op)(*args)

    ours("so3", SO3, "exp", phi)
    ours("so3", SO3, "log", R1)
    ours("so3", SO3, "compose", R1, R2)
    ours("se3", SE3, "exp", xi)
    ours("se3", SE3, "log", T1)
    ours("se3", SE3, "compose", T1, T2)
    ours("r3so3", R3SO3, "exp", xi)
    ours("r3so3", R3SO3, "log", P1)
    ours("r3so3", R3SO3, "compose", P1, P2)

    if "kornia" in peers:
        from kornia.geometry.liegroup import Se3, So3

        kq1, kq2 = So3.from_matrix(R1), So3.from_matrix(R2)
        kt1, kt2 = Se3.from_matrix(T1), Se3.from_matrix(T2)
        cases["so3", "exp"]["kornia"] = lambda: So3.exp(phi)
        cases["so3", "log"]["kornia"] = lambda: kq1.log()
        cases["so3", "compose"]["kornia"] = lambda: kq1 * kq2
        cases["se3", "exp"]["kornia"] = lambda: Se3.exp(xi)
        cases["se3", "log"]["kornia"] = lambda: kt1.log()
        cases["se3", "compose"]["kornia"] = lambda: kt1 * kt2
    if "pytorch_kinematics" in peers:
        pk = peers["pytorch_kinematics"]
        cases["so3", "exp"]["pytorch_kinematics"] = lambda: pk.so3_exp_map(phi)
        cases["so3", "exp"]["pytorch_kinematics[quat]"] = lambda: pk.quaternion_to_matrix(
            pk.axis_angle_to_quaternion(phi)
        )
        cases["so3", "log"]["pytorch_kinematics"] = lambda: pk.so3_log_map(R1)
        cases["so3", "log"]["pytorch_kinematics[quat]"] = lambda: pk.matrix_to_axis_angle(R1)
    if "roma" in peers:
        roma = peers["roma"]
        rq1, rq2 = roma.rotmat_to_unitquat(R1), roma.rotmat_to_unitquat(R2)
        rr1 = roma.RigidUnitQuat(rq1, T1[:, :3, 3].contiguous())
        rr2 = roma.RigidUnitQuat(rq2, T2[:, :3, 3].contiguous())
        cases["so3", "exp"]["roma"] = lambda: roma.rotvec_to_rotmat(phi)
        cases["so3", "exp"]["roma[quat]"] = lambda: roma.rotvec_to_unitquat(phi)
        cases["so3", "log"]["roma"] = lambda: roma.rotmat_to_rotvec(R1)
        cases["so3", "log"]["roma[quat]"] = lambda: roma.unitquat_to_rotvec(rq1)
        cases["so3", "compose"]["roma[quat]"] = lambda: roma.quat_product(rq1, rq2)
        cases["se3", "compose"]["roma[quat]"] = lambda: rr1 @ rr2
    if "pypose" in peers:
        pp = peers["pypose"]
        pq1, pq2 = pp.mat2SO3(R1.double()).float(), pp.mat2SO3(R2.double()).float()
        pt1, pt2 = pp.mat2SE3(T1.double()).float(), pp.mat2SE3(T2.double()).float()
        cases["so3", "exp"]["pypose"] = lambda: pp.so3(phi).Exp()
        cases["so3", "log"]["pypose"] = lambda: pq1.Log()
        cases["so3", "compose"]["pypose"] = lambda: pq1 * pq2
        cases["se3", "exp"]["pypose"] = lambda: pp.se3(xi).Exp()
        cases["se3", "log"]["pypose"] = lambda: pt1.Log()
        cases["se3", "compose"]["pypose"] = lambda: pt1 * pt2
    assert all(t.dtype == f32 for t in (phi, xi, R1, T1, P1))
    return cases


def time_cases(
    cases: dict[tuple[str, str], dict[str, Callable[[], Any]]], repeats: int
) -> tuple[dict[tuple[str, str, str], list[float]], dict[tuple[str, str, str], float]]:
    times: dict[tuple[str, str, str], list[float]] = {}
    warmup: dict[tuple[str, str, str], float] = {}
    with torch.inference_mode():
        for (group, op), impls in cases.items():
            for impl, fn in impls.items():
                t0 = time.perf_counter()
                fn()  # compiles the compiled variants; first-touch for everyone
                fn()
                warmup[group, op, impl] = time.perf_counter() - t0
        for _ in range(repeats):  # interleaved rounds: contention hits every library alike
            for (group, op), impls in cases.items():
                for impl, fn in impls.items():
                    t0 = time.perf_counter()
                    fn()
                    times.setdefault((group, op, impl), []).append(time.perf_counter() - t0)
    return times, warmup


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="batch size (elements per call)")
    ap.add_argument("--repeats", type=int, default=15, help="timed rounds")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--no-compiled", action="store_true", help="skip the torch.compile variants")
    ap.add_argument("--out", type=Path, default=None, help="JSON output path")
    ap.add_argument("--tuned-malloc", action="store_true", help="re-run with glibc keeping large blocks")
    args = ap.parse_args()
    if args.tuned_malloc and any(os.environ.get(k) != v for k, v in MALLOC_ENV.items()):
        # glibc reads these at process start: re-execute with them set
        os.execve(sys.executable, [sys.executable, *sys.argv], {**os.environ, **MALLOC_ENV})
    if args.out is None:
        args.out = TUNED if args.tuned_malloc else RESULTS

    torch.set_num_threads(args.threads)
    peers = _peers_available()
    cases = build_cases(args.n, not args.no_compiled, peers)
    times, warmup = time_cases(cases, args.repeats)

    rows = []
    for (group, op, impl), ts in times.items():
        med = statistics.median(ts)
        rows.append(
            {
                "group": group,
                "op": op,
                "impl": impl,
                "median_ms": med * 1e3,
                "melem_per_s": args.n / med / 1e6,
                "first_two_calls_s": warmup[group, op, impl],
            }
        )
    summary = []
    print(
        f"\nN = {args.n:,} float32, {args.threads} threads, median of {args.repeats} interleaved rounds "
        f"(OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
        f"malloc {'tuned' if args.tuned_malloc else 'glibc defaults'})\n"
    )
    header = f"{'group':6} {'op':8} {'implementation':26} {'Melem/s':>9} {'ms':>8}"
    print(header)
    print("-" * len(header))
    for group, op in cases:
        sub = sorted(
            (r for r in rows if r["group"] == group and r["op"] == op), key=lambda r: -r["melem_per_s"]
        )
        for r in sub:
            print(f"{group:6} {op:8} {r['impl']:26} {r['melem_per_s']:9.2f} {r['median_ms']:8.2f}")
        peer_rows = [r for r in sub if not r["impl"].startswith("posediff")]
        best_peer = max(peer_rows, key=lambda r: r["melem_per_s"]) if peer_rows else None
        for mine in (r for r in sub if r["impl"].startswith("posediff")):
            ratio = mine["melem_per_s"] / best_peer["melem_per_s"] if best_peer else None
            summary.append(
                {
                    "group": group,
                    "op": op,
                    "impl": mine["impl"],
                    "fastest_peer": best_peer["impl"] if best_peer else None,
                    "ratio": ratio,
                    "meets_goal": (ratio >= GOAL) if ratio is not None else None,
                }
            )
        print()
    print(f"{'group':6} {'op':8} {'posediff variant':20} {'fastest peer':26} {'ratio':>6}  goal ≥ {GOAL}×")
    for s in summary:
        ratio = f"{s['ratio']:.2f}" if s["ratio"] is not None else "  n/a"
        verdict = {True: "yes", False: "NO", None: "(no peer)"}[s["meets_goal"]]
        print(f"{s['group']:6} {s['op']:8} {s['impl']:20} {str(s['fastest_peer']):26} {ratio:>6}  {verdict}")

    meta = {
        "command": "OMP_WAIT_POLICY=PASSIVE python " + " ".join(["benchmarks/lie_ops.py", *sys.argv[1:]]),
        "note": "the default run's JSON keeps the peers' native element types; see the module docstring",
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "n": args.n,
        "dtype": "float32",
        "threads": args.threads,
        "repeats": args.repeats,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "malloc": "tuned (" + ", ".join(f"{k}={v}" for k, v in MALLOC_ENV.items()) + ")"
        if args.tuned_malloc
        else "glibc defaults",
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "peers": {k: getattr(v, "__version__", "?") for k, v in peers.items()},
    }
    atomic_write_json(args.out, {"meta": meta, "results": rows, "summary": summary})
    print(f"\nwrote {args.out}")
    return 0


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    sys.exit(main())
