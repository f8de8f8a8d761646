"""Which classes a configuration read from a file may name: the allow-list for stored run configs.

A ``posediff fit`` checkpoint stores its resolved run config, and ``eval`` / ``predict`` /
``load_checkpoint`` / ``fit ckpt_path=`` rebuild the model from it with Hydra's ``instantiate``.
``torch.load(weights_only=True)`` keeps pickled code out, but ``instantiate`` calls whatever a
``_target_`` names (``builtins.open``, ``pathlib.Path.write_text``, …) and imports the module it
lives in. So before anything of a stored config is built or resolved, :func:`check_config` walks
it and refuses, in one line naming the key:

* a ``_target_`` that is not in the allow-list (posediff's own groups, kernels, schedules,
  samplers, diffusion, encoders, denoisers, modules, data modules and augmentations, plus the
  Lightning and posediff pieces of the trainer config, which are checked but never built from a
  file) — a dotted name is compared as a string, no module is imported on its account;
* ``_target_`` in a section that is built from the file (``module``, ``data``) naming a trainer
  piece (callback, logger, ``lightning.Trainer``);
* an OmegaConf interpolation (``${...}``): fit stores resolved configs, and resolvers may import
  modules by name;
* anything but plain dicts, lists, strings, numbers, booleans and ``None``.

An out-of-tree class (your own group, kernel, sampler, …) is allowed by the code that defines it:
a :class:`~posediff.lie.LieGroup` subclass is allowed once imported (it is in the registry), any
other class with :func:`allow_target` — a file can never extend the list.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

#: Classes a stored ``module`` / ``data`` section may build (their public names, as conf/ spells them).
BUILDABLE: frozenset[str] = frozenset(
    {
        # groups
        "posediff.lie.SO3",
        "posediff.lie.SE3",
        "posediff.lie.R3SO3",
        "posediff.lie.SE2",
        # diffusion
        "posediff.diffusion.Diffusion",
        "posediff.diffusion.ConcentratedGaussian",
        "posediff.diffusion.IGSO3",
        "posediff.diffusion.LinearSchedule",
        "posediff.diffusion.LogLinearSchedule",
        "posediff.diffusion.PowerSchedule",
        "posediff.diffusion.GeodesicRandomWalk",
        "posediff.diffusion.AncestralSampler",
        "posediff.diffusion.FewStepSampler",
        "posediff.diffusion.HeunSampler",
        "posediff.diffusion.CrouchGrossmanSampler",
        "posediff.diffusion.RKMKSampler",
        "posediff.diffusion.FlowEulerSampler",
        "posediff.diffusion.FlowHeunSampler",
        # networks and modules
        "posediff.nn.ResNetEncoder",
        "posediff.nn.PoseEncoder",
        "posediff.nn.MLPDenoiser",
        "posediff.models.PoseDiffusionModule",
        "posediff.models.PoseRegressionModule",
        # data
        "posediff.data.SymmetryToyDataModule",
        "posediff.data.symsol.SymsolDataModule",
        "posediff.data.bop.BopDataModule",
        "posediff.data.official.SymsolOfficialDataModule",
        "posediff.data.official.SymsoltOfficialDataModule",
        "posediff.data.bop.augment.HardAugment",
    }
)

#: Pieces of the stored trainer config: checked (a file naming anything else is refused), never built.
TRAINER_ONLY: frozenset[str] = frozenset(
    {
        "lightning.Trainer",
        "lightning.pytorch.Trainer",
        "lightning.pytorch.callbacks.ModelCheckpoint",
        "lightning.pytorch.callbacks.LearningRateMonitor",
        "lightning.pytorch.callbacks.EMAWeightAveraging",
        "lightning.pytorch.loggers.CSVLogger",
        "lightning.pytorch.loggers.TensorBoardLogger",
        "posediff.training.callbacks.progress_bar",
        "posediff.training.callbacks.ProgressLog",
        "posediff.training.callbacks.TestCurve",
        "posediff.training.checkpoint_io.AtomicCheckpointIO",
        "posediff.evaluation.report.ReportCallback",
    }
)

#: Dotted names of classes that moved, old → new: checkpoints written before a move still load (the
#: stored config is read under the old name, checked as the new one and built from the new one).
RENAMED: dict[str, str] = {
    "posediff.module.PoseDiffusionModule": "posediff.models.PoseDiffusionModule",
    "posediff.regression.PoseRegressionModule": "posediff.models.PoseRegressionModule",
    "posediff.callbacks.progress_bar": "posediff.training.callbacks.progress_bar",
    "posediff.callbacks.ProgressLog": "posediff.training.callbacks.ProgressLog",
    "posediff.callbacks.TestCurve": "posediff.training.callbacks.TestCurve",
    "posediff.checkpoint_io.AtomicCheckpointIO": "posediff.training.checkpoint_io.AtomicCheckpointIO",
    "posediff.report.ReportCallback": "posediff.evaluation.report.ReportCallback",
}

#: Sections of a stored run config that posediff builds objects from.
BUILT_SECTIONS: tuple[str, ...] = ("module", "data", "group", "diffusion", "denoiser", "encoder", "sampler",
                                   "kernel", "schedule")  # fmt: skip

_SPECIAL = {"_target_", "_args_", "_partial_", "_convert_", "_recursive_"}
_extra: set[str] = set()


class UntrustedConfigError(ValueError):
    """A stored config that names something posediff does not build from files."""


def allow_target(target: str | type) -> str:
    """Allow one more class in stored configs (call it from the code that defines the class; returns
    its dotted name). Configs read from files can never call this."""
    name = target if isinstance(target, str) else f"{target.__module__}.{target.__qualname__}"
    _extra.add(name)
    return name


def _canonical() -> set[str]:
    """``module.qualname`` of every allowed posediff class (the names Hydra's ``_locate`` may also see);
    importing posediff's own packages is all this does."""
    from hydra.utils import get_object

    names: set[str] = set()
    for public in BUILDABLE:
        obj = get_object(public)
        names.add(f"{obj.__module__}.{obj.__qualname__}")
    return names


_CANONICAL: set[str] | None = None


def buildable_targets() -> set[str]:
    """Every dotted name a built section may use: :data:`BUILDABLE`, their defining modules'
    spellings, registered (already imported) Lie groups and :func:`allow_target` additions."""
    global _CANONICAL
    if _CANONICAL is None:
        _CANONICAL = _canonical()
    from ..lie import LieGroup

    groups = {f"{c.__module__}.{c.__qualname__}" for c in LieGroup.registry.values()}
    return set(BUILDABLE) | _CANONICAL | groups | _extra


def _walk(node: Any, path: str) -> Iterator[tuple[str, Any]]:
    yield path, node
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _walk(v, f"{path}.{k}" if path else str(k))
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            yield from _walk(v, f"{path}[{i}]")


def check_config(config: Any, where: str = "stored config") -> None:
    """Raise :class:`UntrustedConfigError` (one line, the key named) unless every ``_target_`` in
    ``config`` is allowed for its section and the tree is plain data without interpolations."""
    if not isinstance(config, dict):
        raise UntrustedConfigError(f"{where}: the run config is a {type(config).__name__}, not a mapping")
    buildable = buildable_targets()
    for path, node in _walk(config, ""):
        key = path or "<root>"
        if isinstance(node, dict):
            bad = [k for k in node if not isinstance(k, str)]
            if bad:
                raise UntrustedConfigError(f"{where}: key {bad[0]!r} under {key} is not a string")
            if "_target_" in node:
                target = node["_target_"]
                section = path.split(".", 1)[0].split("[", 1)[0]
                allowed = buildable if section in BUILT_SECTIONS else buildable | TRAINER_ONLY
                if not isinstance(target, str) or RENAMED.get(target, target) not in allowed:
                    raise UntrustedConfigError(
                        f"{where}: {key}._target_ = {target!r} is not a class posediff builds from "
                        f"a file (refused; nothing was run). If it is your own class, call "
                        f"posediff.config.allow_target({target!r}) in your code first"
                    )
            elif "_args_" in node:
                raise UntrustedConfigError(f"{where}: {key} has _args_ but no _target_ (refused)")
            odd = [k for k in node if k.startswith("_") and k.endswith("_") and k not in _SPECIAL]
            if odd:
                raise UntrustedConfigError(f"{where}: {key}.{odd[0]} is not a Hydra key posediff uses")
        elif isinstance(node, str):
            if "${" in node:
                raise UntrustedConfigError(
                    f"{where}: {key} holds an interpolation {node[:60]!r}; stored configs are resolved "
                    "plain values (refused; nothing was resolved)"
                )
        elif not (node is None or isinstance(node, (bool, int, float, list, tuple))):
            raise UntrustedConfigError(f"{where}: {key} holds a {type(node).__name__}, not plain config data")


def target_class(config: dict[str, Any], where: str = "stored config") -> type:
    """The class an allowed ``config['_target_']`` names (posediff's modules only are imported)."""
    from hydra.utils import get_class

    target = config.get("_target_") if isinstance(config, dict) else None
    target = RENAMED.get(target, target) if isinstance(target, str) else target
    if not isinstance(target, str) or target not in buildable_targets():
        raise UntrustedConfigError(f"{where}: _target_ {target!r} is not a class posediff builds from a file")
    return get_class(target)


def upgrade_config(config: Any) -> Any:
    """``config`` with every ``_target_`` of :data:`RENAMED` replaced by its new name (a copy; plain
    data in, plain data out). :func:`check_config` accepts a config in either spelling."""
    if isinstance(config, dict):
        out = {k: upgrade_config(v) for k, v in config.items()}
        target = out.get("_target_")
        if isinstance(target, str) and target in RENAMED:
            out["_target_"] = RENAMED[target]
        return out
    if isinstance(config, list):
        return [upgrade_config(v) for v in config]
    return config


__all__ = [
    "BUILDABLE",
    "BUILT_SECTIONS",
    "RENAMED",
    "TRAINER_ONLY",
    "UntrustedConfigError",
    "allow_target",
    "buildable_targets",
    "check_config",
    "target_class",
    "upgrade_config",
]
