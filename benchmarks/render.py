"""Rendering speed of SYMSOL-T on the CPU, against the time a training step spends per image.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/render.py          # 224 px and 64 px
    python benchmarks/render.py --quick --out /tmp/render.json    # smoke run

What is timed (SYMSOL-T uniform poses, all five shapes interleaved; scene 2 ray casts in NumPy, no GL):

* **render** — ``SymsolRenderer.render`` alone in this process (RGB + depth);
* **shards, 1 / 2 processes** — ``render_dataset`` into a temporary folder (render, deflate, write),
  with ``workers=1`` and ``workers=2`` (spawned processes, startup included);
* **DataLoader, 0 / 2 workers** — batches of 16 from ``SymsolDataModule(mode="render")``, the
  render-on-the-fly training path (worker startup included);
* **train step** — forward + backward + Adam step of a torchvision ResNet18 (the encoder of the
  CPU preset; ``weights=None``) on a batch of 16 images at the same size, 2 intra-op threads: what
  rendering must stay below so that training is never render-bound.

Numbers are images per second and milliseconds per image (medians over ``--repeats`` rounds).
Results: a table on stdout and ``benchmarks/results/render.json``.
"""

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _median_rate(fn, n: int, repeats: int) -> float:  # noqa: ANN001
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(n / (time.perf_counter() - t0))
    return statistics.median(rates)


def bench_size(size: int, n: int, repeats: int) -> dict[str, float]:
    import torch

    from posediff.data.symsol import SymsolDataModule, SymsolRenderer, render_dataset, sample_poses

    out: dict[str, float] = {}
    poses = sample_poses("symsolt", "uniform", "train", max(1, n // 5), seed=0)
    r = SymsolRenderer(size)
    r.render(0, poses.R[0], poses.t[0])  # context + scenes

    def render_all() -> None:
        for i in range(len(poses)):
            r.render(int(poses.shape_id[i]), poses.R[i], poses.t[i])

    out["render"] = _median_rate(render_all, len(poses), repeats)
    r.close()
    for workers in (1, 2):
        rates = []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as tmp:
                s = render_dataset(
                    tmp,
                    split="train",
                    n_per_shape=max(1, n // 5),
                    image_size=size,
                    shard_size=64,
                    workers=workers,
                    progress=False,
                )
                rates.append(s.images / s.seconds)
        out[f"shards_{workers}"] = statistics.median(rates)
    for workers in (0, 2):
        dm = SymsolDataModule(
            "symsolt",
            "uniform",
            mode="render",
            image_size=size,
            n_per_shape_train=max(1, n // 5),
            batch_size=16,
            num_workers=workers,
        )
        dm.setup("fit")

        def load_all(dm: SymsolDataModule = dm) -> None:
            for _ in dm.train_dataloader():
                pass

        out[f"loader_{workers}"] = _median_rate(load_all, (len(dm.train) // 16) * 16, repeats)

    import torchvision

    torch.manual_seed(0)
    net = torchvision.models.resnet18(weights=None)
    opt = torch.optim.Adam(net.parameters(), 1e-4)
    x = torch.rand(16, 3, size, size)

    def step() -> None:
        opt.zero_grad()
        net(x).square().mean().backward()
        opt.step()

    step()
    out["train_step"] = _median_rate(step, 16, max(3, repeats))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[224, 64])
    ap.add_argument("--images", type=int, default=400, help="images per timed round (multiple of 5)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="50 images, 1 round")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "render.json"))
    args = ap.parse_args()
    if args.quick:
        args.images, args.repeats = 50, 1
    import torch

    torch.set_num_threads(2)
    results = {}
    for size in args.sizes:
        results[str(size)] = bench_size(size, args.images, args.repeats)
    head = "| size | render (1 process) | shards, 1 process | shards, 2 processes | DataLoader, 0 workers | DataLoader, 2 workers | ResNet18 train step |"
    lines = [head, "|" + "---|" * 7]
    for size, r in results.items():
        cells = [
            f"{r[k]:.0f} img/s ({1000 / r[k]:.1f} ms)"
            for k in ("render", "shards_1", "shards_2", "loader_0", "loader_2", "train_step")
        ]
        lines.append(f"| {size} px | " + " | ".join(cells) + " |")
    print("\n".join(lines))
    doc = {
        "meta": {
            "command": "python benchmarks/render.py" + (" --quick" if args.quick else ""),
            "date": dt.datetime.now().isoformat(timespec="seconds"),
            "images_per_round": args.images,
            "repeats": args.repeats,
            "cpu": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "load_average": list(os.getloadavg()),
            "torch": torch.__version__,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "units": "images per second (median over rounds)",
        },
        "results": results,
    }
    from posediff._io import atomic_write_json

    path = atomic_write_json(args.out, doc)
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
