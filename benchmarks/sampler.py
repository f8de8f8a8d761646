"""Time per denoising step of every sampler, split into the network and the group math.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/sampler.py            # N = 1000 × B = 1, float32, 2 threads
    python benchmarks/sampler.py --quick                            # smoke run (few repeats, eager only)
    python benchmarks/sampler.py --no-compiled --out /tmp/s.json    # skip the torch.compile variant
    python benchmarks/sampler.py --images                           # images/s of the quickstart model, batches of images

The setting of the issue: 1000 hypotheses for 1 condition (a random 512-d feature), the default
MLP denoiser (``conf/denoiser/mlp.yaml``: hidden 256, one Fourier block pair, 128 frequencies),
the default diffusion (concentrated Gaussian, linear schedule, σ-scaled score output, kernel
prior), each registered sampler with its ``conf/sampler`` defaults, for SO(3) and SE(3), under
``torch.no_grad`` on 2 intra-op threads. Goal: the group math is at most 10 % of a step.

What is timed is the production path: ``Sampler.sample(module.denoise_fn(), feature, N, S)`` of a
``PoseDiffusionModule``, whose ``forward`` takes ``group.log`` of the noisy poses, maps σ to the
level index (``schedule.level``) and calls the denoiser. Three ``time.perf_counter`` probes sit
on that path: around the whole ``denoise_fn`` call, around ``group.log`` and around the denoiser
(MLP) call inside it.
Per step, with S steps per ``sample`` call (the prior draw is included, amortised over S):

* **network** — the MLP forward alone;
* **group math** — everything else in the step: ``group.log`` and ``schedule.level`` in the
  module's ``forward`` (reported apart as *log* and *level*), ``Diffusion.to_score``, the σ arithmetic,
  the noise draws, the ``rplus`` updates (``X · Exp(ξ)``) and the sampler's Python overhead
  (reported apart as *update*).

Every case is timed ``repeats`` times, interleaved round by round (contention on a shared machine
hits every case alike), after two warm-up calls; the table shows medians over the rounds (the share
is the median of the per-round shares). ``eager`` uses the groups' eager kernels; ``compiled``
uses ``LieGroup(compiled=True)`` (``torch.compile``d kernels; compile time reported apart, not
counted). Results: a table on stdout and ``benchmarks/results/sampler.json``.

The share depends on the load: the network (large GEMMs) slows down more under contention than
the group math (many small, latency-bound ops), so a busy machine *lowers* the group share. Judge
the goal on a quiet machine.
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from rich.console import Console
from rich.table import Table
from torch import Tensor, nn

from posediff._io import atomic_write_json
from posediff.diffusion import ConcentratedGaussian, Diffusion, LinearSchedule, Sampler
from posediff.lie import SE3, SO3
from posediff.models import PoseDiffusionModule
from posediff.nn import MLPDenoiser

warnings.filterwarnings("ignore")
RESULTS = Path(__file__).resolve().parent / "results" / "sampler.json"
GOAL = 0.10  # group math / step
GROUPS = {"so3": SO3, "se3": SE3}
COND_DIM = 512


class Stopwatch:
    """Accumulated wall time of the calls it wraps."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.calls = 0

    def reset(self) -> None:
        self.seconds = 0.0
        self.calls = 0

    def wrap(self, fn: Callable[..., Tensor]) -> Callable[..., Tensor]:
        def timed(*args: Any) -> Tensor:
            t0 = time.perf_counter()
            out = fn(*args)
            self.seconds += time.perf_counter() - t0
            self.calls += 1
            return out

        return timed


class TimedDenoiser(nn.Module):
    """The MLP denoiser with a stopwatch around its forward (the "network" part)."""

    def __init__(self, net: nn.Module, watch: Stopwatch) -> None:
        super().__init__()
        self.net = net
        self._forward = watch.wrap(net)

    def forward(self, tangent: Tensor, level: Tensor, feature: Tensor) -> Tensor:
        return self._forward(tangent, level, feature)


@dataclass
class Case:
    group: str
    impl: str
    sampler: str
    run: Callable[[], Tensor]
    net: Stopwatch
    fn: Stopwatch
    logw: Stopwatch
    calls_per_run: int
    warmup_s: float = 0.0
    total: list[float] = field(default_factory=list)
    network: list[float] = field(default_factory=list)
    denoise_fn: list[float] = field(default_factory=list)
    log: list[float] = field(default_factory=list)


def build_cases(n: int, steps: int, impls: list[str], seed: int) -> list[Case]:
    """One case per (group, eager/compiled, sampler); the same weights and feature for a group."""
    cases = []
    for gname, gcls in GROUPS.items():
        torch.manual_seed(seed)
        dim = gcls().dim
        mlp = MLPDenoiser(cond_dim=COND_DIM, in_dim=dim, out_dim=dim).eval()
        feature = torch.randn(1, COND_DIM, generator=torch.Generator().manual_seed(seed))
        for impl in impls:
            for sname, scls in Sampler.registry.items():
                net, fn, logw = Stopwatch(), Stopwatch(), Stopwatch()
                group = gcls(compiled=impl == "compiled")
                group.log = logw.wrap(group.log)  # only PoseDiffusionModule.forward calls log in a step
                diffusion = Diffusion(ConcentratedGaussian(group), LinearSchedule())
                module = PoseDiffusionModule(diffusion, TimedDenoiser(mlp, net), scls).eval()
                sampler = module.sampler
                denoise_fn = fn.wrap(module.denoise_fn())
                gen = torch.Generator().manual_seed(seed)

                def run(sampler=sampler, denoise_fn=denoise_fn, feature=feature, gen=gen) -> Tensor:
                    return sampler.sample(denoise_fn, feature, n, steps, gen)

                calls = sampler.network_calls(steps)
                cases.append(Case(gname, impl, sname, run, net, fn, logw, calls))
    return cases


def time_cases(cases: list[Case], repeats: int) -> None:
    with torch.no_grad():
        for c in cases:
            t0 = time.perf_counter()
            out = c.run()  # compiles the compiled variants; first touch for everyone
            c.run()
            c.warmup_s = time.perf_counter() - t0
            if not torch.isfinite(out).all():
                print(f"warning: {c.group}/{c.impl}/{c.sampler} produced non-finite poses", file=sys.stderr)
        for _ in range(repeats):  # interleaved rounds
            for c in cases:
                c.net.reset()
                c.fn.reset()
                c.logw.reset()
                t0 = time.perf_counter()
                c.run()
                c.total.append(time.perf_counter() - t0)
                c.network.append(c.net.seconds)
                c.denoise_fn.append(c.fn.seconds)
                c.log.append(c.logw.seconds)
                if c.net.calls != c.calls_per_run:
                    raise RuntimeError(
                        f"{c.sampler}: {c.net.calls} network calls, expected {c.calls_per_run}"
                    )


def summarise(c: Case, steps: int) -> dict[str, Any]:
    med = statistics.median
    ms = 1e3 / steps
    group = [t - n for t, n in zip(c.total, c.network, strict=True)]
    share = [g / t for g, t in zip(group, c.total, strict=True)]
    return {
        "group": c.group,
        "impl": c.impl,
        "sampler": c.sampler,
        "network_calls_per_step": c.calls_per_run / steps,
        "step_ms": med(c.total) * ms,
        "step_ms_min": min(c.total) * ms,
        "network_ms": med(c.network) * ms,
        "group_math_ms": med(group) * ms,
        "log_ms": med(c.log) * ms,
        "level_ms": med([f - n - lg for f, n, lg in zip(c.denoise_fn, c.network, c.log, strict=True)]) * ms,
        "update_ms": med([t - f for t, f in zip(c.total, c.denoise_fn, strict=True)]) * ms,
        "group_share": med(share),
        "meets_goal": med(share) <= GOAL,
        "warmup_s": c.warmup_s,
        "raw_s": {"total": c.total, "network": c.network, "denoise_fn": c.denoise_fn, "log": c.log},
    }


IMAGES_RESULTS = Path(__file__).resolve().parent / "results" / "sampler_images.json"


def images(args: argparse.Namespace) -> int:
    """``--images``: whole-image throughput of the quickstart model (the ``make demo`` network: a ResNet18
    pose encoder on 64 px crops of 128 px images, the anchored MLP denoiser, R³×SO(3)): batches of B
    images, N hypotheses each, S steps of its few-step sampler — the encoder once per image, the
    denoiser batched over all B·N hypotheses — eager and with the denoiser step compiled
    (:func:`posediff.evaluation.sampling.accelerated_denoise_fn`). Random weights (the time does not
    depend on them). Writes ``benchmarks/results/sampler_images.json``."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from posediff.cli import config_dir
    from posediff.config import register_resolvers
    from posediff.evaluation.sampling import accelerated_denoise_fn

    torch.set_num_threads(args.threads)
    register_resolvers()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=quickstart"])
    torch.manual_seed(args.seed)
    module = instantiate(cfg.module).eval()
    size = int(cfg.data.image_size)
    rows = []
    plan = [(b, n, st) for b in (1, 16) for n in (1, 64) for st in (5, 10)]
    if args.quick:
        plan = [(1, 1, 5), (16, 64, 5)]
    modes = ["eager"] if args.no_compiled else ["eager", "compiled"]
    t_start = time.perf_counter()
    for mode in modes:
        fn = accelerated_denoise_fn(module, mode)
        for b, n, st in plan:
            image = torch.rand(b, 3, size, size, generator=torch.Generator().manual_seed(0))

            def run(image: Tensor = image, n: int = n, st: int = st, fn: Any = fn) -> None:
                with torch.no_grad():
                    cond = module.encode(image)
                    module.sampler.sample(fn, cond, n, st, torch.Generator().manual_seed(0))

            t0 = time.perf_counter()
            run()
            run()  # warm-up (and compilation)
            warm = time.perf_counter() - t0
            times = []
            for _ in range(max(3, args.repeats // 3)):
                t0 = time.perf_counter()
                run()
                times.append(time.perf_counter() - t0)
            sec = statistics.median(times)
            rows.append({"mode": mode, "batch": b, "hypotheses": n, "steps": st, "images_per_s": b / sec,
                         "s_per_batch": sec, "warmup_s": warm})  # fmt: skip
            print(
                f"{mode:9s} B={b:3d} N={n:3d} S={st:3d}: {b / sec:8.1f} images/s ({1000 * sec / b:.1f} ms/image)"
            )
    meta = {"command": " ".join(["python", "benchmarks/sampler.py", *sys.argv[1:]]),
            "date": dt.datetime.now().isoformat(timespec="seconds"), "model": "+experiment=quickstart (random weights)",
            "image_size": size, "threads": torch.get_num_threads(), "torch": torch.__version__,
            "cpu": _cpu_model(), "cpu_count": os.cpu_count(), "load_average": os.getloadavg(),
            "elapsed_s": round(time.perf_counter() - t_start, 1)}  # fmt: skip
    out = args.out if args.out != RESULTS else IMAGES_RESULTS
    atomic_write_json(out, {"meta": meta, "results": rows})
    print(f"wrote {out}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--images", action="store_true", help="whole-image throughput of the quickstart model (images/s)"
    )
    ap.add_argument("--n", type=int, default=1000, help="hypotheses per condition")
    ap.add_argument("--steps", type=int, default=10, help="denoising steps per sample() call")
    ap.add_argument("--repeats", type=int, default=11, help="timed rounds")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-compiled", action="store_true", help="skip the LieGroup(compiled=True) variant")
    ap.add_argument("--quick", action="store_true", help="smoke run: 3 rounds of 5 steps, eager only")
    ap.add_argument("--out", type=Path, default=RESULTS, help="JSON output path")
    args = ap.parse_args()
    if args.images:
        return images(args)
    if args.quick:
        args.repeats, args.steps, args.no_compiled = 3, 5, True

    torch.set_num_threads(args.threads)
    impls = ["eager"] if args.no_compiled else ["eager", "compiled"]
    t_start = time.perf_counter()
    cases = build_cases(args.n, args.steps, impls, args.seed)
    time_cases(cases, args.repeats)
    rows = [summarise(c, args.steps) for c in cases]

    table = Table(
        title=f"time per denoising step: N = {args.n} hypotheses × B = 1 condition, default MLP, float32, "
        f"{args.threads} threads; median of {args.repeats} rounds of {args.steps} steps",
        caption=f"group math = step − network (log and level in the module's forward + sampler update); "
        f"goal: group share ≤ {GOAL:.0%}. OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}",
    )
    for col in ("group", "lie", "sampler"):
        table.add_column(col)
    for col in ("step ms", "network ms", "group ms", "log ms", "level ms", "update ms", "group %"):
        table.add_column(col, justify="right")
    table.add_column("≤ 10 %", justify="center")
    for r in rows:
        table.add_row(
            r["group"],
            r["impl"],
            r["sampler"],
            f"{r['step_ms']:.2f}",
            f"{r['network_ms']:.2f}",
            f"{r['group_math_ms']:.2f}",
            f"{r['log_ms']:.2f}",
            f"{r['level_ms']:.2f}",
            f"{r['update_ms']:.2f}",
            f"{100 * r['group_share']:.1f}",
            "[green]PASS[/]" if r["meets_goal"] else "[red]FAIL[/]",
        )
    console = Console(width=max(Console().width, 130))
    console.print(table)
    if "compiled" in impls:
        compile_s = {
            f"{r['group']}/{r['sampler']}": round(r["warmup_s"], 2) for r in rows if r["impl"] == "compiled"
        }
        console.print(f"compiled variants, first two sample() calls (incl. compilation), s: {compile_s}")
    elapsed = time.perf_counter() - t_start

    meta = {
        "command": " ".join(["python", "benchmarks/sampler.py", *sys.argv[1:]]),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "goal": f"group math ≤ {GOAL:.0%} of a step",
        "num_hypotheses": args.n,
        "num_conditions": 1,
        "cond_dim": COND_DIM,
        "steps_per_call": args.steps,
        "repeats": args.repeats,
        "quick": args.quick,
        "dtype": "float32",
        "threads": torch.get_num_threads(),
        "grad": "torch.no_grad",
        "denoiser": "MLPDenoiser(cond_dim=512, in_dim=dim, out_dim=dim) — conf/denoiser/mlp.yaml defaults",
        "diffusion": "Diffusion(ConcentratedGaussian(group), LinearSchedule()) — conf/fit.yaml defaults",
        "samplers": {name: repr(cls.__init__.__kwdefaults__) for name, cls in Sampler.registry.items()},
        "split": "network = MLP forward; group math = step − network = log (group.log) + level "
        "(schedule.level and the rest of PoseDiffusionModule.forward) + update (to_score, noise, rplus, Python)",
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "elapsed_s": round(elapsed, 1),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg(),
    }
    atomic_write_json(args.out, {"meta": meta, "results": rows})
    console.print(f"wrote {args.out} ({elapsed:.0f} s)")
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
