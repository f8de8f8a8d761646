"""Where a checkpoint's translation error comes from: per axis (x, y, depth) and per shape, for the
locator (locate-then-crop encoders), the anchor (the pose head) and the sampled hypotheses (their
mean and each one), on the test split of the checkpoint's own data.

    python benchmarks/translation_errors.py outputs/demo/fit/checkpoints/last.ckpt --per-shape 20

Prints the table and writes JSON (``--out``, default ``benchmarks/results/translation_errors.json``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def measure(ckpt: str, per_shape: int, num_samples: int, num_steps: int, seed: int) -> dict:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from posediff.models import load_checkpoint
    from posediff.symmetry import SHAPES

    m = load_checkpoint(ckpt)
    data = OmegaConf.create(m.config)["data"]
    data.n_per_shape_test = per_shape
    dm = instantiate(data)
    dm.setup("test")
    parts: dict[str, list[torch.Tensor]] = {"locator": [], "anchor": [], "sample_mean": [], "samples": []}
    shapes = []
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for batch in dm.test_dataloader():
            image, t = batch[m.cond_key], batch["pose"][:, :3, 3]
            enc = m.encode_full(image)
            if enc.located is not None:
                parts["locator"].append((enc.located - t).abs())
            if enc.translation is not None:
                parts["anchor"].append((enc.translation - t).abs())
            x = m.sample(image, num_samples, num_steps, generator=gen)[..., :3, 3]
            parts["sample_mean"].append((x.mean(1) - t).abs())
            parts["samples"].append((x - t[:, None]).abs().mean(1))
            shapes.append(batch["shape"])
    shape = torch.cat(shapes)
    out: dict = {}
    for name, rows in parts.items():
        if not rows:
            continue
        err = torch.cat(rows)
        out[name] = {
            "abs_xyz": [round(float(v), 4) for v in err.mean(0)],
            "abs_depth_per_shape": {
                SHAPES[k]: round(float(err[shape == k, 2].mean()), 4) for k in shape.unique().tolist()
            },  # fmt: skip
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpt")
    ap.add_argument("--per-shape", type=int, default=20, help="test images per shape")
    ap.add_argument("--num-samples", type=int, default=50)
    ap.add_argument("--num-steps", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "translation_errors.json"))
    a = ap.parse_args()
    if not Path(a.ckpt).is_file():
        print(f"translation_errors: no checkpoint {a.ckpt} (train one: posediff fit +experiment=quickstart)",
              file=sys.stderr)  # fmt: skip
        return 2
    res = {"command": "python benchmarks/translation_errors.py " + " ".join(sys.argv[1:]),
           "errors": measure(a.ckpt, a.per_shape, a.num_samples, a.num_steps, a.seed)}  # fmt: skip
    from posediff._io import atomic_write_json

    atomic_write_json(Path(a.out), res)
    print("| part | |x| | |y| | |depth| | depth per shape |\n|---|---|---|---|---|")
    for name, r in res["errors"].items():
        per = " / ".join(f"{k} {v:.2f}" for k, v in r["abs_depth_per_shape"].items())
        x, y, z = r["abs_xyz"]
        print(f"| {name} | {x:.3f} | {y:.3f} | {z:.3f} | {per} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
