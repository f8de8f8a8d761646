"""``posediff demo [out=DIR] [fit overrides]``: the first run docs/image-model.md describes, made of the other commands (each
its own Hydra run).

Renders the ``cpu``-preset SYMSOL-T at 128 px (skipped when already there), trains and evaluates
``+experiment=quickstart`` (before and after), and predicts one test image each of a tetrahedron, a
cube and a cylinder. Everything lands in ``out`` (default ``outputs/demo``), which is replaced only
when the whole run succeeded, and only if an earlier demo made it (its ``.posediff-output`` marker;
anything else is refused up front, ``posediff._io``).
"""

from __future__ import annotations

import time
from pathlib import Path

from ..._io import OutputFolderError, check_output_dir, make_output_dir, remove_own_dir, replace_dir
from ..errors import fail

COMMAND = "posediff demo"
#: the cpu preset at 128 px (quickstart crops 64 px from it)
DATA_ROOT = "data/symsolt_scene2_cpu128"


def run(args: list[str]) -> int:
    from ..main import main  # the demo is the other commands, run as a user runs them

    out = Path("outputs/demo")
    fit_overrides = []
    for a in args:
        if a.startswith("out="):
            out = Path(a.split("=", 1)[1])
        else:
            fit_overrides.append(a)
    try:  # before any work: a folder posediff did not make is never replaced or deleted
        check_output_dir(out, COMMAND)
        partial = out.with_name(out.name + ".partial")
        remove_own_dir(partial, COMMAND)
        make_output_dir(partial, COMMAND)
    except OutputFolderError as e:
        return fail(COMMAND, str(e))
    start = time.perf_counter()
    for split in ("train", "test"):
        code = main(["data", "render", "dataset=symsolt", f"split={split}", "image_size=128", f"out={DATA_ROOT}",
                     "progress=false"])  # fmt: skip
        if code:
            return code
    fit_dir = partial / "fit"
    code = main(
        [
            "fit",
            "+experiment=quickstart",
            f"data.root={DATA_ROOT}",
            f"hydra.run.dir={fit_dir}",
            *fit_overrides,
        ]
    )
    if code:
        return code
    ckpt = fit_dir / "checkpoints" / "last.ckpt"
    for shape in ("tet", "cube", "cyl"):
        extra = ["trajectory=true"] if shape == "tet" else []
        code = main(["predict", f"ckpt_path={ckpt}", "index=0", f"+data.shapes=[{shape}]", *extra,
                     f"hydra.run.dir={partial / f'predict_{shape}'}"])  # fmt: skip
        if code:
            return code
    try:
        replace_dir(partial, out, COMMAND)
    except OutputFolderError as e:
        return fail(COMMAND, f"{e} (the finished run is in {partial})")
    minutes = (time.perf_counter() - start) / 60
    summary = (out / "fit" / "metrics.md").read_text().split("## untrained model")[0]
    last = out / "fit" / "checkpoints" / "last.ckpt"
    print(f"\n{summary.strip()}\n")
    print(f"demo finished in {minutes:.1f} min")
    print(f"metrics:  {out / 'fit' / 'metrics.md'} (and metrics.json)")
    print("pictures: " + " ".join(str(p) for p in sorted(out.glob("predict_*/*.png"))))
    print(f"model:    {last}")
    print(f"next:     posediff eval ckpt_path={last} -m sampler.num_steps=5,10,50,100")
    return 0
