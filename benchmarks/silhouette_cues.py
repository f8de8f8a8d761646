"""How much of SYMSOL-T's translation the object's silhouette gives *without* knowing its orientation
(issue 27, item 2): per shape, on a rendered split,

* the depth from the apparent size alone: the spread (std) of ``log z + ½ log a`` (``a`` the silhouette
  area, exact from the render's depth mask) — zero if the area at a given depth did not depend on the
  orientation; also the radius of gyration ``r`` (``log z + log r``), ``det`` of the second moments
  (``log z + ¼ log det``), and the best linear combination of the three (least squares, one fit per
  shape — a floor for any orientation-blind size cue built from these moments);
* the silhouette centroid against the projection of the true translation (pixels): what a
  centroid-based locator would start from.

A log-depth spread ``s`` is a depth error of about ``0.8 · s · z₀`` scene units (mean |error| of a
Gaussian; ``z₀ = 9.09``), so it is what the encoder must remove by seeing the orientation.

    python benchmarks/silhouette_cues.py --root data/symsolt_scene2_cpu128/test

Prints a table and writes JSON (``--out``, default ``benchmarks/results/silhouette_cues.json``).
No network is involved.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def load(root: Path) -> tuple[np.ndarray, np.ndarray, torch.Tensor, dict]:
    """shape ids ``(N,)``, translations ``(N, 3)`` (camera frame, as ``index.npz`` holds them) and depth masks ``(N, H, W)`` of a split."""
    meta = json.loads((root / "meta.json").read_text())
    idx = np.load(root / "index.npz")
    shard, offset = idx["shard"], idx["offset"]
    masks = []
    cache: dict[int, np.ndarray] = {}
    for k, o in zip(shard.tolist(), offset.tolist(), strict=True):
        if k not in cache:
            cache.clear()
            with np.load(root / f"shard-{k:05d}.npz") as z:
                cache[k] = z["depth"]
        masks.append(cache[k][o] > 0)
    return idx["shape_id"], idx["t"], torch.tensor(np.stack(masks), dtype=torch.float64), meta


def measure(root: Path, fov_deg: float = 60.0) -> dict:
    from posediff.symmetry import SHAPES

    sid, t, m, meta = load(root)
    n, h, w = m.shape
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    a = m.sum((1, 2))
    cx, cy = (m * xs).sum((1, 2)) / a, (m * ys).sum((1, 2)) / a
    dx, dy = xs - cx[:, None, None], ys - cy[:, None, None]
    ixx, iyy, ixy = (
        (m * dx * dx).sum((1, 2)) / a,
        (m * dy * dy).sum((1, 2)) / a,
        (m * dx * dy).sum((1, 2)) / a,
    )
    det = ixx * iyy - ixy**2
    focal = (w / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    tt = torch.tensor(t, dtype=torch.float64)
    z = tt[:, 2]
    u, v = focal * tt[:, 0] / z + w / 2.0, focal * tt[:, 1] / z + h / 2.0
    out: dict = {"root": str(root), "images": int(n), "image_size": int(w), "shapes": {}}
    for k in sorted(set(sid.tolist())):
        s = torch.tensor(sid == k)
        lz = z[s].log()
        cues = {"area": 0.5 * a[s].log(), "gyration": 0.5 * (ixx + iyy)[s].log(), "det": 0.25 * det[s].log()}
        row = {name: float((lz + c).std()) for name, c in cues.items()}
        x = torch.stack([*cues.values(), torch.ones_like(lz)], 1)
        fit = torch.linalg.lstsq(x, -lz[:, None]).solution
        row["linear"] = float(((x @ fit)[:, 0] + lz).std())
        row["centroid_px"] = [float((cx[s] - u[s]).abs().mean()), float((cy[s] - v[s]).abs().mean())]
        row["images"] = int(s.sum())
        out["shapes"][SHAPES[int(k)]] = row
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=ROOT / "data" / "symsolt_scene2_cpu128" / "test")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "silhouette_cues.json")
    args = ap.parse_args()
    if not (args.root / "index.npz").is_file():
        print(f"silhouette_cues: no rendered split at {args.root} (make one: posediff data render dataset=symsolt "
              f"split=test image_size=128 out={args.root.parent})", file=sys.stderr)  # fmt: skip
        return 2
    res = {"command": "python benchmarks/silhouette_cues.py " + " ".join(sys.argv[1:]), **measure(args.root)}
    from posediff._io import atomic_write_json

    atomic_write_json(args.out, res)
    z0 = 5.25 / math.tan(math.radians(30.0))
    print(
        "| shape | log-depth std: area | gyration | det | linear (3 cues) | ≈ depth error, area / linear | centroid − projection, px (x / y) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, r in res["shapes"].items():
        e = [0.8 * r[c] * z0 for c in ("area", "linear")]
        print(f"| {name} | {r['area']:.4f} | {r['gyration']:.4f} | {r['det']:.4f} | {r['linear']:.4f} | "
              f"{e[0]:.2f} / {e[1]:.2f} | {r['centroid_px'][0]:.2f} / {r['centroid_px'][1]:.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
