"""``posediff <command> [overrides]``: one table of commands over Hydra.

Each command that takes configuration has a primary config ``conf/<command>.yaml`` and accepts
everything Hydra does (``key=value`` overrides, ``-m`` multirun, ``--cfg job``, ``--help``); its code is
``posediff.cli.commands.<verb>.run(cfg) -> int``, imported when the command runs.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from .errors import DISK_ERRNOS, disk_line, fail, hydra_line, one_line

_PKG = Path(__file__).resolve().parents[1]  # src/posediff (or site-packages/posediff)


@dataclass(frozen=True)
class Command:
    """A ``posediff`` command: its one-line ``help``, its primary Hydra ``config`` (``None``: none) and
    ``run``, the ``module:function`` under :mod:`posediff.cli.commands` that does it."""

    help: str
    config: str | None
    run: str | None  # None: a table of subcommands (``data``: :data:`DATA_COMMANDS`)

    def load(self) -> Callable[..., int]:
        module, _, function = str(self.run).partition(":")
        return getattr(importlib.import_module(f"posediff.cli.commands.{module}"), function)


COMMANDS: dict[str, Command] = {
    "groups": Command("list the registered Lie groups and their tensor layouts", None, "groups:run"),
    "check": Command("run the Lie group contract on a group from config: posediff check group=so3", "check",
                     "check:run"),
    "fit": Command("train a score model and evaluate it: posediff fit +experiment=toy_so3", "fit", "fit:run"),
    "pretrain": Command(
        "train the image encoder by symmetry-aware regression on posediff's renders, write its weights: "
        "posediff pretrain [out=FILE]",
        "pretrain",
        "fit:pretrain",
    ),
    "eval": Command(
        "evaluate a checkpoint: posediff eval ckpt_path=CKPT [-m sampler.num_steps=5,10,50,100]", "eval",
        "eval:run",
    ),
    "predict": Command(
        "pose hypotheses, modes and plots for one image: posediff predict ckpt_path=CKPT image=IMG.png",
        "predict",
        "predict:run",
    ),
    "export": Command(
        "write a checkpoint's encoder, denoiser and sampling loop for other runtimes: "
        "posediff export ckpt_path=CKPT format=onnx|torchscript|exported_program out=DIR",
        "export",
        "export:run",
    ),
    "distill": Command(
        "a few-step student of a trained diffusion model, as a normal checkpoint: "
        "posediff distill ckpt_path=TEACHER steps=5 [max_steps=N] [out=FILE]",
        "distill",
        "distill:run",
    ),
    "score": Command(
        "score a BOP19 results CSV (any method's) on a BOP dataset: posediff score csv=PATH data.root=DIR",
        "score",
        "score:run",
    ),
    "report": Command("one table from an eval multirun: posediff report dir=multirun/eval/<stamp>", "report",
                      "report:run"),
    "demo": Command(
        "render a small SYMSOL-T, train `quickstart` on the CPU, evaluate, predict: posediff demo [out=DIR] [fit overrides]",
        None,
        "demo:run",
    ),
    "data": Command("make datasets: posediff data render|grid|make-bop [key=value ...]", None, None),
}  # fmt: skip

#: ``posediff data <subcommand>``.
DATA_COMMANDS: dict[str, Command] = {
    "render": Command(
        "render a SYMSOL / SYMSOL-T split into shards: posediff data render dataset=symsolt split=train out=DIR",
        "render",
        "data:render",
    ),
    "grid": Command(
        "a picture of the five shapes: posediff data grid out=symsolt_grid.png", "grid", "data:grid"
    ),
    "make-bop": Command(
        "a small BOP-format dataset (3 objects, PBR/real/test splits): posediff data make-bop out=DIR",
        "make_bop",
        "data:make_bop",
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


def input_error_line(e: BaseException) -> str | None:
    """The one line of an error the user can fix (:func:`posediff.cli.errors.one_line`), also when Hydra
    or a DataLoader worker wrapped it; ``None`` for anything else (a bug, shown with its traceback)."""
    return one_line(e)


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


#: options whose values are paths: ``~`` is expanded, and characters Hydra's grammar reserves
#: (``= , [ ] ' "``, spaces, non-ASCII letters) are quoted for the user
PATH_KEYS = ("ckpt_path", "image", "csv", "out", "dir", "data.root", "encoder.weights", "hydra.run.dir",
             "hydra.sweep.dir")  # fmt: skip
_PLAIN = re.compile(r"[A-Za-z0-9_./:@%+-]*")


def prepare_args(args: Sequence[str], multirun: bool) -> list[str]:
    """The command line as Hydra should read it: path values (:data:`PATH_KEYS`) with ``~`` expanded
    and quoted where Hydra's grammar would split or refuse them (a comma too, unless ``-m`` makes it
    a sweep); every other argument unchanged."""
    out = []
    for arg in args:
        key, eq, value = arg.partition("=")
        if not eq or key.lstrip("+~") not in PATH_KEYS or value[:1] in ("'", '"') or "${" in value:
            out.append(arg)
            continue
        if value.startswith("~"):
            value = os.path.expanduser(value)
        if not _PLAIN.fullmatch(value) and not (multirun and "," in value):
            quote = '"' if "'" in value else "'"
            escaped = value.replace(quote, "\\" + quote)  # Hydra: a backslash escapes only a quote
            value = quote + escaped + ("\\" if escaped.endswith("\\") else "") + quote
        out.append(f"{key}={value}")
    return out


#: what a run folder holds once a run wrote there (Hydra's record, posediff's outputs)
RUN_FILES = ("metrics.json", "poses.json", "poses.npz", "checkpoints", "distill.json", "progress.log")


def _run_dir_problem(name: str, args: Sequence[str]) -> str | None:
    """Why the Hydra run / sweep folder of ``args`` cannot be written (a file in its path, no
    permission, another run's files in it), checked before Hydra creates it; ``None`` when it can.

    A folder that holds another run's files (:data:`RUN_FILES`) is refused — runs never mix — except
    for ``fit`` resuming a checkpoint of that very folder (``ckpt_path=<dir>/checkpoints/…``)."""
    from .._io import OutputFolderError, check_output_dir

    multirun = any(a in ("-m", "--multirun") for a in args)
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    folder = "multirun" if multirun else "outputs"
    given = False
    values = {a.split("=", 1)[0].lstrip("+"): a.split("=", 1)[1] for a in args if "=" in a}
    if key in values:
        folder, given = values[key], True
    if "${" in folder:
        return None  # an interpolation: Hydra resolves it
    try:
        check_output_dir(folder, "run", replace=False, key=key)
    except OutputFolderError as e:
        return str(e)
    path = Path(folder)
    relaunched = os.environ.get("LOCAL_RANK", "0") != "0" or os.environ.get("NODE_RANK", "0") != "0"
    if given and path.is_dir() and name != "report" and not relaunched:  # DDP ranks > 0 share rank 0's folder
        held = [f for f in RUN_FILES if (path / f).exists()]
        ckpt = values.get("ckpt_path")
        resume = name == "fit" and ckpt and Path(ckpt).resolve().is_relative_to(path.resolve())
        if held and not resume:
            return (
                f"{key}={folder} holds another run's files ({', '.join(held)}); runs never share a "
                "folder — give a new one (or resume that run: posediff fit ckpt_path="
                f"{path / 'checkpoints' / 'last.ckpt'} {key}={folder})"
            )
    return None


def _run_hydra(name: str, cmd: Command, args: list[str]) -> int:
    """``cmd`` under ``hydra.main`` with ``args``: the command-line checks Hydra does not make first
    (an unknown config choice, an unwritable or occupied run folder), then every numeric option
    (:func:`posediff.options.check_options`), then ``cmd.run``; Hydra's own errors as one line."""
    import hydra
    from omegaconf import DictConfig

    from ..config import new_run_id, register_resolvers
    from ..options import check_options
    from .errors import reports_input_errors

    register_resolvers()
    new_run_id()  # outputs/<command>/<time>_<token>: a folder of its own even in the same second
    conf = config_dir()
    prefix = f"posediff {name}"
    if not (conf / f"{cmd.config}.yaml").exists():
        return fail(
            "posediff",
            f"no config {cmd.config}.yaml in {conf} (set POSEDIFF_CONFIG_DIR to a posediff conf/ folder)",
        )
    multirun = any(a in ("-m", "--multirun") for a in args)
    plain = [a if "=" not in a or not a.partition("=")[2].startswith("~") else
             f"{a.partition('=')[0]}={os.path.expanduser(a.partition('=')[2])}" for a in args]  # fmt: skip
    problem = _unknown_config_choice(plain, conf)
    if problem:
        return fail("posediff", problem)
    problem = _run_dir_problem(name, plain)
    if problem:
        return fail(prefix, problem)
    task = cmd.load()
    codes: list[int] = []
    state = {"in_task": False}

    @reports_input_errors(name)
    def checked(cfg: DictConfig) -> int:
        check_options(cfg)  # every numeric option, before anything is built
        return task(cfg)

    def _main(cfg: DictConfig) -> None:
        state["in_task"] = True
        codes.append(checked(cfg))

    # argparse cannot take overrides on both sides of a flag: `posediff eval a=1 -m b=1,2` is
    # documented usage, so Hydra's -m/--multirun goes first
    flags = [a for a in args if a in ("-m", "--multirun")]
    rest = prepare_args([a for a in args if a not in flags], multirun)
    argv = sys.argv
    # Lightning's DDP launcher re-executes sys.argv for the other ranks: make that a runnable script
    os.environ["POSEDIFF_COMMAND"] = name
    user_full_error = os.environ.get("HYDRA_FULL_ERROR")
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")  # Hydra raises instead of printing 3-6 lines; see below
    sys.argv = [str(Path(__file__).resolve().parent / "_relaunch.py"), *flags, *rest]
    try:
        hydra.main(config_path=str(conf), config_name=cmd.config, version_base="1.3")(_main)()
    except Exception as e:
        if user_full_error or state["in_task"]:
            raise  # a bug in a task (input errors were taken above), or the user asked for Hydra's trace
        message = hydra_line(e, rest) or one_line(e)
        if message is None:
            raise
        return fail(prefix, message)
    finally:
        sys.argv = argv
        if user_full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
    if len(codes) > 1 and any(codes):
        failed = sum(1 for c in codes if c)
        fail(
            prefix, f"{failed} of {len(codes)} jobs failed (each said why above; posediff report lists them)"
        )
    return max(codes, default=0)


def main(argv: Sequence[str] | None = None) -> int:
    """``posediff <command> ...``: the exit code (0 ok, 2 bad input, 130 interrupted, 141 output
    closed early — ``posediff ... | head -1`` ends quietly, as Unix tools do)."""
    try:
        code = _dispatch(list(sys.argv[1:] if argv is None else argv))
        sys.stdout.flush()  # a full or closed stdout fails here, not in the interpreter's exit
        return code
    except KeyboardInterrupt as e:
        what = f"{e}; " if str(e) else ""
        return fail("posediff", f"interrupted (Ctrl-C); {what}files already written are whole (written to "
                    "temporary names, then renamed)", 130)  # fmt: skip
    except BrokenPipeError:
        _silence_stdout()
        return 141
    except SystemExit as e:  # rich's Console exits 1 on a broken pipe, after pointing stdout elsewhere
        if isinstance(e.__context__, BrokenPipeError):
            _silence_stdout()
            return 141
        raise
    except OSError as e:
        if e.errno not in DISK_ERRNOS:
            raise
        _silence_stdout()
        return fail("posediff", disk_line(e))


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's last flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _dispatch(args: list[str]) -> int:
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, rest = args[0], args[1:]
    cmd = COMMANDS.get(name)
    if cmd is None:
        return fail(
            "posediff", f"unknown command {name!r}; available: {', '.join(COMMANDS)} (see posediff --help)"
        )
    if name == "data":
        sub = rest[0] if rest else ""
        if sub in ("", "-h", "--help"):
            width = max(map(len, DATA_COMMANDS))
            print("usage: posediff data <subcommand> [key=value ...]\n\nsubcommands:")
            print("\n".join(f"  {k:<{width}}  {c.help}" for k, c in DATA_COMMANDS.items()))
            return 0 if sub else 2
        if sub not in DATA_COMMANDS:
            return fail("posediff", f"unknown data subcommand {sub!r}; available: {', '.join(DATA_COMMANDS)}")
        return _run_hydra(f"data {sub}", DATA_COMMANDS[sub], rest[1:])
    if cmd.config is not None:
        return _run_hydra(name, cmd, rest)
    if rest and rest[0] in ("-h", "--help"):
        print(f"posediff {name}: {cmd.help}")
        return 0
    return cmd.load()(rest)


def entrypoint() -> None:
    sys.exit(main())


__all__ = ["COMMANDS", "DATA_COMMANDS", "Command", "PATH_KEYS", "config_dir", "entrypoint", "input_error_line",
           "main", "prepare_args", "usage"]  # fmt: skip
