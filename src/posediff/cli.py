"""``posediff <command> [overrides]``: a thin layer over Hydra that dispatches to ``posediff.tasks``.

Each command that takes configuration has a primary config ``conf/<command>.yaml`` and accepts
everything Hydra does (``key=value`` overrides, ``-m`` multirun, ``--cfg job``, ``--help``).
"""

import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

_PKG = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Command:
    help: str
    config: str | None  # primary Hydra config name; None for commands that take no config


COMMANDS: dict[str, Command] = {
    "groups": Command("list the registered Lie groups and their tensor layouts", None),
    "check": Command("run the Lie group contract on a group from config: posediff check group=so3", "check"),
    "fit": Command("train a score model and evaluate it: posediff fit +experiment=toy_so3", "fit"),
    "pretrain": Command(
        "train the image encoder by symmetry-aware regression on posediff's renders, write its weights: "
        "posediff pretrain [out=FILE]",
        "pretrain",
    ),
    "eval": Command(
        "evaluate a checkpoint: posediff eval ckpt_path=CKPT [-m sampler.num_steps=5,10,50,100]", "eval"
    ),
    "predict": Command(
        "pose hypotheses, modes and plots for one image: posediff predict ckpt_path=CKPT image=IMG.png",
        "predict",
    ),
    "export": Command(
        "write a checkpoint's encoder, denoiser and sampling loop for other runtimes: "
        "posediff export ckpt_path=CKPT format=onnx|torchscript|exported_program out=DIR",
        "export",
    ),
    "distill": Command(
        "a few-step student of a trained diffusion model, as a normal checkpoint: "
        "posediff distill ckpt_path=TEACHER steps=5 [max_steps=N] [out=FILE]",
        "distill",
    ),
    "score": Command(
        "score a BOP19 results CSV (any method's) on a BOP dataset: posediff score csv=PATH data.root=DIR",
        "score",
    ),
    "report": Command("one table from an eval multirun: posediff report dir=multirun/eval/<stamp>", "report"),
    "demo": Command(
        "render a small SYMSOL-T, train `quickstart` on the CPU, evaluate, predict: posediff demo [out=DIR] [fit overrides]",
        None,
    ),
    "data": Command("make datasets: posediff data render|grid|make-bop [key=value ...]", None),
}

#: ``posediff data <subcommand>``.
DATA_COMMANDS: dict[str, Command] = {
    "render": Command(
        "render a SYMSOL / SYMSOL-T split into shards: posediff data render dataset=symsolt split=train out=DIR",
        "render",
    ),
    "grid": Command("a picture of the five shapes: posediff data grid out=symsolt_grid.png", "grid"),
    "make-bop": Command(
        "a small BOP-format dataset (3 objects, PBR/real/test splits): posediff data make-bop out=DIR",
        "make_bop",
    ),
}


def config_dir() -> Path:
    """Where the Hydra configs live: $POSEDIFF_CONFIG_DIR, the repository's conf/, or the packaged copy."""
    env = os.environ.get("POSEDIFF_CONFIG_DIR")
    if env:
        return Path(env).resolve()
    repo = _PKG.parents[1] / "conf"
    if (repo / "check.yaml").exists():
        return repo
    return _PKG / "_conf"


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [
        "usage: posediff <command> [key=value ...] [-m] [--help]",
        "",
        "posediff: 6D object pose as a distribution, by score-based diffusion on Lie groups.",
        "",
        "commands:",
        *(f"  {name:<{width}}  {cmd.help}" for name, cmd in COMMANDS.items()),
        "",
        "`posediff <command> --help` shows a command's configuration options (Hydra).",
    ]
    return "\n".join(lines)


def _fail(message: str, code: int = 2, prefix: str = "posediff") -> int:
    print(f"{prefix}: {message}", file=sys.stderr)
    return code


def _unknown_config_choice(args: Sequence[str], conf: Path) -> str | None:
    """A one-line error for ``group=nope`` style overrides that name no config file."""
    if any(a.startswith("hydra.searchpath") for a in args):
        return None  # options may come from elsewhere; let Hydra decide
    for arg in args:
        if arg.startswith(("-", "~")) or "=" not in arg:
            continue
        key, value = arg.lstrip("+").split("=", 1)
        folder = conf / key
        if "." in key or not folder.is_dir() or "," in value or value in ("null", ""):
            continue
        if key.startswith("hydra/"):  # Hydra's own groups also hold its plugins' options (submitit_slurm …)
            continue
        options = sorted(p.stem for p in folder.glob("*.yaml"))
        if value not in options:
            return f"unknown {key} {value!r}; available: {', '.join(options)}"
    return None


def input_error_line(e: BaseException) -> str | None:
    """The one line of an input error posediff raised (a ``ValueError`` / ``OSError`` subclass defined
    in posediff: checkpoints, data, outputs), also when Hydra or a DataLoader worker wrapped it;
    ``None`` for anything else (a bug, shown with its traceback)."""
    seen = 0
    while e is not None and seen < 8:
        cls = type(e)
        if cls.__module__.startswith("posediff") and issubclass(cls, (ValueError, OSError)):
            lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
            if not lines:
                return cls.__name__
            if lines[0].startswith("Caught ") and len(lines) > 1:  # re-raised from a DataLoader worker
                last = lines[-1]
                return last.split(": ", 1)[1] if last.startswith(cls.__name__ + ":") else last
            return lines[0]
        e, seen = e.__cause__ or e.__context__, seen + 1
    return None


def _run_dir_problem(args: Sequence[str]) -> str | None:
    """Why the Hydra run / sweep folder of ``args`` cannot be written (a file in its path, no
    permission), checked before Hydra creates it; ``None`` when it can."""
    from ._io import OutputFolderError, check_output_dir

    multirun = any(a in ("-m", "--multirun") for a in args)
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    folder = "multirun" if multirun else "outputs"
    for a in args:
        if a.startswith(key + "="):
            folder = a.split("=", 1)[1]
    if "${" in folder:
        return None  # an interpolation: Hydra resolves it
    try:
        check_output_dir(folder, "run", replace=False, key=key)
    except OutputFolderError as e:
        return str(e)
    return None


def _run_hydra(name: str, cmd: Command, args: list[str]) -> int:
    import hydra
    from omegaconf import DictConfig

    from . import tasks
    from .config import register_resolvers
    from .data.bop import commands as bop_commands
    from .data.symsol import commands as symsol_commands

    register_resolvers()
    task: Callable[[DictConfig], int] = {
        "check": tasks.check_group,
        "fit": tasks.fit,
        "pretrain": tasks.pretrain,
        "eval": tasks.evaluate_checkpoint,
        "predict": tasks.predict,
        "report": tasks.report,
        "score": tasks.score,
        "export": tasks.export_checkpoint,
        "distill": tasks.distill,
        "data render": symsol_commands.render_data,
        "data grid": symsol_commands.render_grid,
        "data make-bop": bop_commands.make_bop,
    }[name]
    conf = config_dir()
    if not (conf / f"{cmd.config}.yaml").exists():
        return _fail(
            f"no config {cmd.config}.yaml in {conf} (set POSEDIFF_CONFIG_DIR to a posediff conf/ folder)"
        )
    problem = _unknown_config_choice(args, conf)
    if problem:
        return _fail(problem)
    problem = _run_dir_problem(args)
    if problem:
        return _fail(problem, prefix=f"posediff {name}")
    result: dict[str, int] = {}

    def _main(cfg: DictConfig) -> None:
        from omegaconf.errors import MissingMandatoryValue

        try:
            result["code"] = task(cfg)
        except MissingMandatoryValue as e:
            key = e.full_key or "a key"
            result["code"] = _fail(
                f"{key} is required ({key}=...; posediff {name} --help lists the options)",
                prefix=f"posediff {name}",
            )
        except Exception as e:  # noqa: BLE001 - posediff's own input errors become one line; others propagate
            message = input_error_line(e)
            if message is None:
                raise
            result["code"] = _fail(message, prefix=f"posediff {name}")

    # argparse cannot take overrides on both sides of a flag: `posediff eval a=1 -m b=1,2` is
    # documented usage, so Hydra's -m/--multirun goes first
    flags = [a for a in args if a in ("-m", "--multirun")]
    args = flags + [a for a in args if a not in flags]
    argv = sys.argv
    # Lightning's DDP launcher re-executes sys.argv for the other ranks: make that a runnable script
    os.environ["POSEDIFF_COMMAND"] = name
    sys.argv = [str(_PKG / "_relaunch.py"), *args]
    try:
        hydra.main(config_path=str(conf), config_name=cmd.config, version_base="1.3")(_main)()
    finally:
        sys.argv = argv
    return result.get("code", 0)


def main(argv: Sequence[str] | None = None) -> int:
    """``posediff <command> ...``: the exit code (0 ok, 2 bad input, 130 interrupted)."""
    try:
        return _main(argv)
    except KeyboardInterrupt as e:
        what = f"{e}; " if str(e) else ""
        print(f"posediff: interrupted (Ctrl-C); {what}files already written are whole (written to temporary "
              "names, then renamed)", file=sys.stderr)  # fmt: skip
        return 130


def _main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, rest = args[0], args[1:]
    cmd = COMMANDS.get(name)
    if cmd is None:
        return _fail(f"unknown command {name!r}; available: {', '.join(COMMANDS)} (see posediff --help)")
    if name == "data":
        sub = rest[0] if rest else ""
        if sub in ("", "-h", "--help"):
            width = max(map(len, DATA_COMMANDS))
            print("usage: posediff data <subcommand> [key=value ...]\n\nsubcommands:")
            print("\n".join(f"  {k:<{width}}  {c.help}" for k, c in DATA_COMMANDS.items()))
            return 0 if sub else 2
        if sub not in DATA_COMMANDS:
            return _fail(f"unknown data subcommand {sub!r}; available: {', '.join(DATA_COMMANDS)}")
        return _run_hydra(f"data {sub}", DATA_COMMANDS[sub], rest[1:])
    if name == "demo":
        if rest and rest[0] in ("-h", "--help"):
            print(f"posediff demo: {cmd.help}")
            return 0
        return _demo(rest)
    if cmd.config is None:
        if rest and rest[0] in ("-h", "--help"):
            print(f"posediff {name}: {cmd.help}")
            return 0
        if rest:
            return _fail(f"{name} takes no arguments, got {' '.join(rest)}")
        from . import tasks

        return tasks.list_groups()
    return _run_hydra(name, cmd, rest)


def _demo(args: list[str]) -> int:
    """``posediff demo``: the README's first run, made of the other commands (each its own Hydra run).

    Renders the ``cpu``-preset SYMSOL-T at 128 px (skipped when already there), trains and evaluates
    ``+experiment=quickstart`` (before and after), and predicts one test image each of a
    tetrahedron, a cube and a cylinder. Everything lands in ``out`` (default ``outputs/demo``),
    which is replaced only when the whole run succeeded, and only if an earlier demo made it (its
    ``.posediff-output`` marker; anything else is refused up front, ``posediff._io``).
    """
    import time

    from ._io import OutputFolderError, check_output_dir, make_output_dir, remove_own_dir, replace_dir

    out = Path("outputs/demo")
    fit_overrides = []
    for a in args:
        if a.startswith("out="):
            out = Path(a.split("=", 1)[1])
        else:
            fit_overrides.append(a)
    try:  # before any work: a folder posediff did not make is never replaced or deleted
        check_output_dir(out, "posediff demo")
        partial = out.with_name(out.name + ".partial")
        remove_own_dir(partial, "posediff demo")
        make_output_dir(partial, "posediff demo")
    except OutputFolderError as e:
        print(f"posediff demo: {e}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    data_root = "data/symsolt_uniform_cpu128"  # the cpu preset at 128 px (quickstart crops 64 px from it)
    for split in ("train", "test"):
        code = main(
            ["data", "render", "dataset=symsolt", f"split={split}", "image_size=128", f"out={data_root}",
             "progress=false"]
        )  # fmt: skip
        if code:
            return code
    fit_dir = partial / "fit"
    code = main(
        [
            "fit",
            "+experiment=quickstart",
            f"data.root={data_root}",
            f"hydra.run.dir={fit_dir}",
            *fit_overrides,
        ]
    )
    if code:
        return code
    ckpt = fit_dir / "checkpoints" / "last.ckpt"
    for shape in ("tet", "cube", "cyl"):
        extra = ["trajectory=true"] if shape == "tet" else []
        code = main(
            ["predict", f"ckpt_path={ckpt}", "index=0", f"+data.shapes=[{shape}]", *extra,
             f"hydra.run.dir={partial / f'predict_{shape}'}"]
        )  # fmt: skip
        if code:
            return code
    try:
        replace_dir(partial, out, "posediff demo")
    except OutputFolderError as e:
        print(f"posediff demo: {e} (the finished run is in {partial})", file=sys.stderr)
        return 2
    minutes = (time.perf_counter() - start) / 60
    summary = (out / "fit" / "metrics.md").read_text().split("## untrained model")[0]
    print(f"\n{summary.strip()}\n")
    print(f"demo finished in {minutes:.1f} min")
    print(f"metrics:  {out / 'fit' / 'metrics.md'} (and metrics.json)")
    print("pictures: " + " ".join(str(p) for p in sorted(out.glob("predict_*/*.png"))))
    print(f"model:    {out / 'fit' / 'checkpoints' / 'last.ckpt'}")
    print(
        f"next:     posediff eval ckpt_path={out / 'fit' / 'checkpoints' / 'last.ckpt'} -m sampler.num_steps=5,10,50,100"
    )
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
