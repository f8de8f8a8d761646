"""A checkpoint on the paper authors' own SYMSOL-T renders, beside posediff's (issue 44).

    python benchmarks/authors_images.py demo=outputs/demo/fit/checkpoints/last.ckpt
    python benchmarks/authors_images.py long=outputs/long/checkpoints/last.ckpt --root /data/symsolt_authors
    python benchmarks/authors_images.py --silhouettes-only

Each ``NAME=CKPT`` is evaluated with one hypothesis per image, as the authors evaluate:

* on a folder in the authors' layout (``--root``, default ``../shared/symsolt_authors_dev``: 200 test
  images, 40 per shape, written by their generator) through ``data=symsolt_official`` — the images
  are resized to the checkpoint's size by ``posediff eval`` itself;
* on the checkpoint's own test data (posediff's renders, as stored in the checkpoint), unless
  ``--no-own``.

It also checks the geometry the reader serves: posediff's meshes rendered at the served poses against
the authors' silhouettes (IoU of the masks, the authors' mask being their non-black pixels) and the
grey-level difference where both show the object. Results are merged into
``benchmarks/results/authors_images.{json,md}`` (a run keeps the other names' blocks), each block
with the commands that made it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_ROOT = ROOT.parent / "shared" / "symsolt_authors_dev"
SHAPES = ("tet", "cube", "icosa", "cone", "cyl")


def _eval(ckpt: str, extra: list[str]) -> tuple[dict[str, Any], str]:
    """``posediff eval`` of ``ckpt`` (one hypothesis per image) in a scratch folder: its result and command."""
    with tempfile.TemporaryDirectory() as tmp:
        args = ["eval", f"ckpt_path={ckpt}", "num_samples=1", *extra]
        subprocess.run(
            [sys.executable, "-m", "posediff.cli", *args, f"hydra.run.dir={tmp}"], check=True, cwd=ROOT
        )
        metrics = json.loads((Path(tmp) / "metrics.json").read_text())
    return _table(metrics), "posediff " + " ".join(args)


def _table(metrics: Any) -> dict[str, Any]:
    """The first ``{"shapes": …, "overall": …}`` block of an eval's metrics.json."""
    if isinstance(metrics, dict):
        if "shapes" in metrics and "overall" in metrics:
            keys = ("spread_deg", "translation_error", "recall_rot@5", "inputs")
            return {
                "shapes": {
                    s: {k: v for k, v in r.items() if k in keys} for s, r in metrics["shapes"].items()
                },
                "overall": {k: v for k, v in metrics["overall"].items() if k in keys},
            }
        for v in metrics.values():
            found = _table(v)
            if found:
                return found
    return {}


def silhouettes(root: Path) -> dict[str, Any]:
    """posediff's meshes at the poses the reader serves against the authors' images: per shape the
    smallest and mean mask IoU and the mean absolute grey difference (0–255) where both are object."""
    import numpy as np
    from PIL import Image

    from posediff.data.official.symsolt import _Records, _split_folder
    from posediff.data.symsol.render import SCENE_DISTANCE, SymsolRenderer

    records = _Records(_split_folder(root, "test"), SHAPES, False)
    renderer = SymsolRenderer(224)
    out: dict[str, Any] = {}
    for k, shape in enumerate(SHAPES):
        ious, diffs = [], []
        for i in np.nonzero(records.label == k)[0]:
            t = records.translation[i].astype(np.float64) + np.array([0.0, 0.0, SCENE_DISTANCE])
            ours = renderer.render(shape, records.rotation[i], t)
            theirs = np.asarray(Image.open(records.files[i]).convert("L"), dtype=np.float64)
            if theirs.shape != ours.mask.shape:
                theirs = np.asarray(Image.open(records.files[i]).convert("L").resize(ours.mask.shape[::-1]))
            mask = theirs > 0
            ious.append(float((ours.mask & mask).sum() / max(1, (ours.mask | mask).sum())))
            both = ours.mask & mask
            diffs.append(float(np.abs(ours.rgb[..., 0].astype(np.float64) - theirs)[both].mean()))
        out[shape] = {"images": len(ious), "iou_min": min(ious), "iou_mean": float(np.mean(ious)),
                      "grey_mae": float(np.mean(diffs))}  # fmt: skip
    return out


def markdown(results: dict[str, Any]) -> str:
    lines = ["# A checkpoint on the authors' SYMSOL-T renders and on posediff's (issue 44)", ""]
    lines += [
        "One hypothesis per image; spread (°, the smallest angle to an equivalent ground truth) / translation",
        "error (scene units). *authors'*: images written by the paper authors' own generator (their Open3D",
        "renderer), read with `data=symsolt_official` and resized to the checkpoint's size by `posediff eval`;",
        "*posediff's*: the checkpoint's own test split. Made by `python benchmarks/authors_images.py`; every",
        "block's commands are in authors_images.json. `study_*`: the look study at the demo's budget",
        "(`+experiment=quickstart`, 2500 steps, one thread each): `study_paper_threshold` trained on the paper's",
        "look (`posediff data render look=paper`) with the thresholded size cue, `study_varied_filled` on a look",
        "drawn per image (`look=varied`) with `encoder.area_estimate=filled` (docs/image-model.md).",
        "",
        "| checkpoint | images | " + " | ".join(SHAPES) + " | overall | authors' / posediff's |",
        "|---|---|" + "---|" * len(SHAPES) + "---|---|",
    ]
    for name, block in results.get("checkpoints", {}).items():
        own = block.get("posediff")
        for which in ("authors", "posediff"):
            res = block.get(which)
            if not res:
                continue
            cells = [
                f"{res['shapes'][s]['spread_deg']:.1f}° / {res['shapes'][s]['translation_error']:.3f}"
                if s in res["shapes"]
                else "–"
                for s in SHAPES
            ]
            o = res["overall"]
            ratio = ""
            if which == "authors" and own:
                ratio = (
                    f"{o['spread_deg'] / own['overall']['spread_deg']:.2f}× spread, "
                    f"{o['translation_error'] / own['overall']['translation_error']:.2f}× t"
                )
            label = {"authors": "authors'", "posediff": "posediff's"}[which]
            lines.append(
                f"| `{name}` | {label} | " + " | ".join(cells)
                + f" | **{o['spread_deg']:.1f}° / {o['translation_error']:.3f}** | {ratio} |"
            )  # fmt: skip
    sil = results.get("silhouettes")
    if sil:
        lines += [
            "",
            "## The geometry served: posediff's meshes at the served poses on the authors' images",
            "",
            f"{sil['root']}: mask IoU (the authors' mask: their non-black pixels, so a face shaded pure black",
            "counts against it) and the mean absolute grey difference where both show the object (0–255).",
            "",
            "| shape | images | IoU min | IoU mean | grey MAE |",
            "|---|---|---|---|---|",
        ]
        for s in SHAPES:
            r = sil["shapes"][s]
            lines.append(
                f"| {s} | {r['images']} | {r['iou_min']:.4f} | {r['iou_mean']:.4f} | {r['grey_mae']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="*", help="NAME=CKPT pairs")
    parser.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="a folder in the authors' layout")
    parser.add_argument("--no-own", action="store_true", help="skip the checkpoint's own test data")
    parser.add_argument("--silhouettes-only", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS / "authors_images")
    args = parser.parse_args(argv)
    from posediff._io import atomic_write_json, atomic_write_text

    json_path = args.out.with_suffix(".json")
    results: dict[str, Any] = json.loads(json_path.read_text()) if json_path.is_file() else {}
    results.setdefault("checkpoints", {})
    sil = silhouettes(args.root)
    results["silhouettes"] = {
        "root": str(args.root),
        "command": f"python benchmarks/authors_images.py --silhouettes-only --root {args.root}",
        "shapes": sil,
    }
    for pair in [] if args.silhouettes_only else args.checkpoints:
        name, _, ckpt = pair.partition("=")
        if not ckpt:
            parser.error(f"give NAME=CKPT, got {pair!r}")
        block: dict[str, Any] = {"ckpt": ckpt, "commands": {}}
        block["authors"], block["commands"]["authors"] = _eval(
            ckpt, ["data=symsolt_official", f"data.root={args.root}"]
        )
        if not args.no_own:
            block["posediff"], block["commands"]["posediff"] = _eval(ckpt, [])
        results["checkpoints"][name] = block
        atomic_write_json(json_path, results)
        atomic_write_text(args.out.with_suffix(".md"), markdown(results))
    atomic_write_json(json_path, results)
    atomic_write_text(args.out.with_suffix(".md"), markdown(results))
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
