"""Forward + backward of the group kernels under autograd: eager against ``LieGroup(compiled=True)``.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/lie_grad.py            # N = 2·10⁵, float32, 2 threads

Under autograd a compiled group runs the compiled kernel forward and a compiled vector-Jacobian
product backward (``posediff.lie.base._CompiledKernel``). Each round times ``op(x)`` plus
``backward`` for both variants, interleaved; the median of the rounds is reported, compile time
(the first two calls) apart. Results: a table on stdout and ``benchmarks/results/lie_grad.json``.
"""

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from posediff._io import atomic_write_json
from posediff.lie import SE3, SO3

RESULTS = Path(__file__).resolve().parent / "results" / "lie_grad.json"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    rows = []
    for group_cls in (SO3, SE3):
        x0 = torch.randn(args.n, group_cls.dim, generator=gen)
        g0 = group_cls().exp(x0)
        for op in ("exp", "log", "compose"):
            fns = {}
            for label, group in (("eager", group_cls()), ("compiled", group_cls(compiled=True))):

                def step(group=group, op=op, x0=x0, g0=g0) -> None:  # type: ignore[no-untyped-def]
                    x = (x0 if op == "exp" else g0).clone().requires_grad_(True)
                    y = group.compose(x, g0.flip(0)) if op == "compose" else getattr(group, op)(x)
                    y.backward(torch.ones_like(y))

                fns[label] = step
            warm = {}
            for label, fn in fns.items():
                t0 = time.perf_counter()
                fn()
                fn()
                warm[label] = time.perf_counter() - t0
            times: dict[str, list[float]] = {k: [] for k in fns}
            for _ in range(args.repeats):
                for label, fn in fns.items():
                    t0 = time.perf_counter()
                    fn()
                    times[label].append(time.perf_counter() - t0)
            med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
            rows.append(
                {
                    "group": group_cls.name,
                    "op": op,
                    "eager_ms": med["eager"],
                    "compiled_ms": med["compiled"],
                    "speedup": med["eager"] / med["compiled"],
                    "compiled_first_two_calls_s": warm["compiled"],
                }
            )
            r = rows[-1]
            print(
                f"{r['group']:4} {op:8} eager {r['eager_ms']:8.2f} ms  compiled {r['compiled_ms']:7.2f} ms"
                f"  {r['speedup']:5.2f}×  (compile {r['compiled_first_two_calls_s']:.1f} s)"
            )
    meta = {
        "command": "OMP_WAIT_POLICY=PASSIVE python " + " ".join(["benchmarks/lie_grad.py", *sys.argv[1:]]),
        "what": "forward + backward (ones as the output gradient), float32, median of interleaved rounds",
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "n": args.n,
        "threads": args.threads,
        "repeats": args.repeats,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
    }
    atomic_write_json(args.out, {"meta": meta, "results": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
