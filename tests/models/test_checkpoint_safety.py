"""A checkpoint cannot run code: tampered stored configs are refused by every command that reads one.

``torch.load(weights_only=True)`` keeps pickles out; these tests are about the stored run config,
which posediff builds objects from. Each payload below really runs when handed to Hydra's
``instantiate`` (checked first, on a sentinel of its own), and must not run — nor be imported or
resolved — through ``load_checkpoint``, ``posediff eval``, ``predict`` or ``fit ckpt_path=``.
"""

import copy
from pathlib import Path
from typing import Any

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from posediff.cli import main
from posediff.config.allowlist import (
    BUILDABLE,
    TRAINER_ONLY,
    UntrustedConfigError,
    allow_target,
    check_config,
)
from posediff.models import CheckpointError, load_checkpoint

TOY = [
    "+experiment=toy_so3",
    "trainer.max_steps=2",
    "trainer.val_check_interval=2",
    "trainer.enable_progress_bar=false",
    "data.num_train=64",
    "data.batch_size=8",
    "data.num_test_per_shape=1",
    "module.num_noisy=4",
    "denoiser.hidden_dim=16",
    "eval.before=false",
    "eval.num_samples=2",
    "eval.num_steps=[2]",
    "eval.samplers=null",
]


@pytest.fixture(scope="module")
def clean_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "run"
    assert main(["fit", *TOY, f"hydra.run.dir={out}"]) == 0
    return out / "checkpoints" / "last.ckpt"


def _open_payload(sentinel: Path) -> dict[str, Any]:
    """``builtins.open(sentinel, "w")``: empties the file."""
    return {"_target_": "builtins.open", "_args_": [str(sentinel), "w"]}


def _write_payload(sentinel: Path) -> dict[str, Any]:
    """``min([0, Path(sentinel).write_text("pwned")])`` — hidden in a number-valued field."""
    write = {
        "_target_": "pathlib.Path.write_text",
        "_args_": [{"_target_": "pathlib.Path", "_args_": [str(sentinel)]}, "pwned"],
    }
    return {"_target_": "builtins.min", "_args_": [[0, write]]}


def _tamper(config: dict[str, Any], sentinel: Path) -> dict[str, dict[str, Any]]:
    """Tampered copies of ``config`` by name."""
    cases: dict[str, dict[str, Any]] = {}

    def case(name: str, edit: Any) -> None:
        c = copy.deepcopy(config)
        edit(c)
        cases[name] = c

    case(
        "group_open",
        lambda c: c["module"]["diffusion"]["kernel"].__setitem__("group", _open_payload(sentinel)),
    )
    case("data_seed_write", lambda c: c["data"].__setitem__("seed", _write_payload(sentinel)))
    case("sampler_write", lambda c: c["module"]["sampler"].__setitem__("_target_", "pathlib.Path.write_text"))
    case("top_group_os", lambda c: c["group"].__setitem__("_target_", "posediff.cli.main.os.system"))
    case("module_target_foreign", lambda c: c["module"].__setitem__("_target_", "builtins.exec"))
    case("trainer_callback", lambda c: c["trainer"]["callbacks"].append(_open_payload(sentinel)))
    case("eval_section", lambda c: c["eval"].__setitem__("samplers", {"x": _write_payload(sentinel)}))
    case(
        "interpolation_import",
        lambda c: c["data"].__setitem__("seed", "${posediff.tangent_dim:antigravity.x}"),
    )
    case("interpolation_env", lambda c: c["data"].__setitem__("root", "${oc.env:HOME}"))
    case("args_without_target", lambda c: c["data"].__setitem__("seed", {"_args_": [1]}))
    return cases


def _save(clean: Path, config: dict[str, Any], path: Path) -> Path:
    ckpt = torch.load(clean, weights_only=True)
    ckpt["posediff_config"] = config
    torch.save(ckpt, path)
    return path


def test_payloads_are_live(tmp_path: Path) -> None:
    """The payloads do run when built by Hydra directly — so the refusals below are meaningful."""
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("keep")
    instantiate(OmegaConf.create({"x": _open_payload(a)})).x.close()
    assert a.read_text() == ""
    assert instantiate(OmegaConf.create({"x": _write_payload(b)})).x == 0 and b.read_text() == "pwned"


def test_clean_checkpoint_passes(clean_ckpt: Path) -> None:
    module = load_checkpoint(clean_ckpt)
    check_config(module.config)


@pytest.mark.parametrize(
    "name",
    ["group_open", "data_seed_write", "sampler_write", "top_group_os", "module_target_foreign",
     "trainer_callback", "eval_section", "interpolation_import", "interpolation_env", "args_without_target"],
)  # fmt: skip
def test_tampered_checkpoint_never_runs(
    name: str, clean_ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sentinel = tmp_path / "precious.txt"
    sentinel.write_text("keep")
    clean = torch.load(clean_ckpt, weights_only=True)["posediff_config"]
    bad = _save(clean_ckpt, _tamper(clean, sentinel)[name], tmp_path / f"{name}.ckpt")

    with pytest.raises(CheckpointError) as err:
        load_checkpoint(bad)
    assert "\n" not in str(err.value) and "refused" in str(err.value)
    capsys.readouterr()
    commands = {
        "eval": ["eval", f"ckpt_path={bad}", f"hydra.run.dir={tmp_path / 'eval'}"],
        "predict": ["predict", f"ckpt_path={bad}", "index=0", f"hydra.run.dir={tmp_path / 'predict'}"],
        "fit": ["fit", *TOY, f"ckpt_path={bad}", f"hydra.run.dir={tmp_path / 'fit'}"],
    }
    for command, args in commands.items():
        assert main(args) == 2, command
        lines = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip()]
        assert len(lines) == 1 and str(bad) in lines[0], (command, lines)
    assert sentinel.read_text() == "keep", "the payload ran"
    assert not (tmp_path / "eval" / "metrics.json").exists()


def test_no_module_imported_on_a_files_word(clean_ckpt: Path, tmp_path: Path) -> None:
    """A foreign dotted name is compared as a string: its module is never imported."""
    import sys

    clean = torch.load(clean_ckpt, weights_only=True)["posediff_config"]
    clean["group"]["_target_"] = "this_module_does_not_exist_xyz.Group"
    clean["module"]["diffusion"]["kernel"]["group"]["_target_"] = "antigravity.Group"
    bad = _save(clean_ckpt, clean, tmp_path / "import.ckpt")
    was = "antigravity" in sys.modules
    with pytest.raises(CheckpointError, match="not a class posediff builds"):
        load_checkpoint(bad)
    assert ("antigravity" in sys.modules) == was


def test_every_config_target_is_allowed() -> None:
    """Every ``_target_`` posediff's own conf/ uses is on the allow-list (a new one must be added)."""
    conf = Path(__file__).resolve().parents[2] / "conf"
    targets = set()
    for path in conf.rglob("*.yaml"):
        for line in path.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            if line.startswith("_target_:"):
                targets.add(line.split(":", 1)[1].strip())
    missing = sorted(t for t in targets if t not in BUILDABLE | TRAINER_ONLY)
    assert not missing, f"add to posediff.config.allowlist: {missing}"


def test_trainer_pieces_are_not_buildable() -> None:
    """A built section may not name a callback or logger (checked, never built, only in trainer)."""
    cfg = {"data": {"_target_": "posediff.training.callbacks.ProgressLog", "path": "x.log"}}
    with pytest.raises(UntrustedConfigError, match="data._target_"):
        check_config(cfg)
    check_config({"trainer": {"callbacks": [{"_target_": "posediff.training.callbacks.ProgressLog"}]}})


def test_allow_target_is_explicit() -> None:
    class MyKernel:  # an out-of-tree class, allowed only by the code that defines it
        pass

    name = f"{MyKernel.__module__}.{MyKernel.__qualname__}"
    with pytest.raises(UntrustedConfigError):
        check_config({"module": {"kernel": {"_target_": name}}})
    assert allow_target(MyKernel) == name
    check_config({"module": {"kernel": {"_target_": name}}})
