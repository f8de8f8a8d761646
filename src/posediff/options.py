"""Bounds of every numeric option and of every size read from a file, checked before anything is built.

One table, :data:`BOUNDS`, keyed by an option's last name (``lr``, ``hidden_dim``, ``num_levels`` …)
or by a dotted tail (``trainer.max_steps``): :func:`check_options` walks a config — a command's
composed Hydra config, or the run config stored in a checkpoint or an export — and refuses the first
value outside its bounds with one line naming the key, its value, the bounds and the config's source.
A value typed as text (``module.lr=abc``) is refused the same way, naming the key.

Bounds are sane, not tight: wide enough for any run posediff's configs describe (the paper's settings
included) and narrow enough that nothing tries to allocate tens of gigabytes, walk a million noise
levels or hand a negative learning rate to the optimizer before a check speaks. A value under an
interpolation (``${seed}``) is checked where it is written, once.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any


class OptionError(ValueError):
    """An option (or a size stored in a file) outside its bounds (one line naming the key)."""


@dataclass(frozen=True)
class Whole:
    """A whole number in ``[least, most]``; ``nullable``: ``null`` allowed; ``allow``: other values."""

    least: int
    most: int
    nullable: bool = False
    allow: tuple[int, ...] = ()

    def problem(self, value: Any) -> str | None:
        if value is None and self.nullable:
            return None
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer() and self.least <= value <= self.most:
                return None  # 1e3 from YAML / a file is a whole number
            return self.describe()
        if value in self.allow or self.least <= value <= self.most:
            return None
        return self.describe()

    def describe(self) -> str:
        extra = f" (or {', '.join(map(str, self.allow))})" if self.allow else ""
        null = " or null" if self.nullable else ""
        if self.least <= -(2**62):  # a type check only: the command checks the range it knows
            return f"a whole number{null}"
        return f"a whole number in [{self.least}, {self.most}]{extra}{null}"


@dataclass(frozen=True)
class Real:
    """A finite number with ``least <(=) value <(=) most`` (``open_low``/``open_high``: strict)."""

    least: float = -math.inf
    most: float = math.inf
    open_low: bool = False
    open_high: bool = False
    nullable: bool = False

    def problem(self, value: Any) -> str | None:
        if value is None and self.nullable:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return self.describe()
        low_ok = value > self.least if self.open_low else value >= self.least
        high_ok = value < self.most if self.open_high else value <= self.most
        return None if low_ok and high_ok else self.describe()

    def describe(self) -> str:
        lo = "(" if self.open_low else "["
        hi = ")" if self.open_high else "]"
        null = " or null" if self.nullable else ""
        return f"a finite number in {lo}{_num(self.least)}, {_num(self.most)}{hi}{null}"


def _num(v: float) -> str:
    if math.isinf(v):
        return "∞" if v > 0 else "-∞"
    return f"{v:g}"


_SIZE = 16_384  # widths of layers: ~1 GB of weights at the most, checked before allocation
_COUNT = 10_000_000  # dataset sizes
_POSITIVE = Real(0.0, open_low=True)
_NONNEG = Real(0.0)
_FRACTION = Real(0.0, 1.0)

#: option name (its last key, or a dotted tail) → bounds. The longest matching tail wins.
BOUNDS: dict[str, Whole | Real] = {
    # run
    "seed": Whole(0, 2**32 - 1),
    "trainer.max_steps": Whole(1, 10**9, allow=(-1,)),
    "trainer.log_every_n_steps": Whole(1, 10**9),
    "trainer.val_check_interval": Whole(1, 10**9, nullable=True),
    "trainer.accumulate_grad_batches": Whole(1, 4096),
    "trainer.gradient_clip_val": Real(0.0, open_low=True, nullable=True),
    # optimisation (module.*)
    "lr": Real(0.0, 10.0, open_low=True),
    "lr_final": Real(0.0, 10.0, open_low=True),
    "denoiser_lr": Real(0.0, 10.0, open_low=True, nullable=True),
    "weight_decay": _NONNEG,
    "decay_start": _FRACTION,
    "num_noisy": Whole(1, 65_536),
    "aux_weight": _NONNEG,
    "locate_weight": _NONNEG,
    "grad_probe_every": Whole(0, 10**9),
    # networks
    "hidden_dim": Whole(1, _SIZE),
    "time_dim": Whole(1, _SIZE),
    "cond_dim": Whole(1, _SIZE),
    "in_dim": Whole(1, _SIZE),
    "out_dim": Whole(1, _SIZE),
    "head_channels": Whole(1, _SIZE),
    "locator_width": Whole(1, _SIZE),
    "num_layers": Whole(1, 256),
    "num_frequencies": Whole(1, 4096),
    "pose_min_period": _POSITIVE,
    "pose_max_period": _POSITIVE,
    "object_radius": _POSITIVE,
    "crop_margin": _POSITIVE,
    "background_level": Real(0.0, 1.0, open_low=True, open_high=True),
    # diffusion
    "num_levels": Whole(2, 10_000),
    "sigma_min": _POSITIVE,
    "sigma_max": _POSITIVE,
    "noise_start": _POSITIVE,
    "noise_end": _POSITIVE,
    "power": _POSITIVE,
    "translation_scale": _POSITIVE,
    "rotation_scale": _POSITIVE,
    # a whole number (or null); its range is the schedule's levels, checked by the command that knows them
    "num_steps": Whole(-(2**62), 2**62, nullable=True),
    "eta": Real(0.0, 1.0),
    "rho": _POSITIVE,
    "renoise": _NONNEG,
    # data
    "image_size": Whole(8, 4096),
    "crop_size": Whole(8, 4096, nullable=True),
    "batch_size": Whole(1, 65_536),
    "num_workers": Whole(0, 256),
    "num_train": Whole(1, _COUNT),
    "num_test_per_shape": Whole(1, _COUNT),
    "num_val_per_shape": Whole(0, _COUNT),
    "n_per_shape": Whole(1, _COUNT),
    "n_per_shape_train": Whole(1, _COUNT),
    "n_per_shape_test": Whole(1, _COUNT, nullable=True),
    "shard_size": Whole(1, 1_000_000),
    "workers": Whole(1, 256),
    "val_fraction": Real(0.0, 1.0, open_high=True),
    "max_val": Whole(0, _COUNT),
    "translation_bound": _POSITIVE,
    "min_visible_px": Whole(0, 10**8),
    "min_visib_fract": _FRACTION,
    "max_train_instances": Whole(1, 10**9, nullable=True),
    "max_test_instances": Whole(1, 10**9, nullable=True),
    "max_val_images": Whole(0, 10**9),
    "dzi_shift": _NONNEG,
    "dzi_scale": _NONNEG,
    "dzi_pad": _POSITIVE,
    # evaluation, prediction, export, distillation
    "num_samples": Whole(1, 100_000),
    "before_num_samples": Whole(1, 100_000, nullable=True),
    "log_likelihood_steps": Whole(2, 10_000),
    "max_inputs": Whole(1, 10**9, nullable=True),
    "index": Whole(0, 10**9, nullable=True),
    "top_modes": Whole(0, 1000),
    "mode_radius_deg": Real(0.0, 180.0, open_low=True),
    "min_mode_weight": Real(0.0, 1.0, open_high=True),
    "vsd_delta": Real(0.0, open_low=True, nullable=True),
    "steps": Whole(-(2**62), 2**62),  # distill: its range is the teacher's levels, checked by the command
    "substeps": Whole(1, 10_000),
    "num_hypotheses": Whole(1, 65_536),
    "reuse": Whole(1, 10_000),
    "max_steps": Whole(1, 10**9, allow=(-1,)),
}

#: subtrees never checked: Hydra's own settings (its parser checks them), logger / callback options.
SKIP = ("hydra", "trainer.logger", "trainer.callbacks", "trainer.plugins")


def _bounds_for(path: str) -> Whole | Real | None:
    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        hit = BOUNDS.get(".".join(parts[-k:]))
        if hit is not None:
            return hit
    return None


def _leaves(node: Any, prefix: str) -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of every leaf under ``node``, skipping interpolations and :data:`SKIP`."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - omegaconf comes with hydra
        DictConfig = ListConfig = ()  # type: ignore[assignment,misc]
    if isinstance(node, DictConfig):
        for key in node.keys():
            path = f"{prefix}.{key}" if prefix else str(key)
            if path in SKIP or OmegaConf.is_interpolation(node, str(key)) or OmegaConf.is_missing(node, key):
                continue
            yield from _leaves(node._get_node(key), path)
        return
    if isinstance(node, ListConfig):
        return  # lists (shapes, step-count lists) are checked by the commands that read them
    if hasattr(node, "_value"):  # an omegaconf ValueNode
        yield prefix, node._value()
        return
    if isinstance(node, Mapping):
        for key, value in node.items():
            path = f"{prefix}.{key}" if prefix else str(key)
            if path in SKIP:
                continue
            yield from _leaves(value, path)
        return
    if isinstance(node, (list, tuple)):
        return
    yield prefix, node


def option_problems(config: Any) -> Iterator[tuple[str, Any, str]]:
    """``(key, value, what it must be)`` for every value of ``config`` outside :data:`BOUNDS`."""
    for path, value in _leaves(config, ""):
        if path.startswith("_") or path.rsplit(".", 1)[-1].startswith("_"):
            continue  # _target_, _partial_ …
        bounds = _bounds_for(path)
        if bounds is None:
            continue
        if isinstance(value, str) and "${" in value:
            continue  # an unresolved interpolation in a plain mapping
        why = bounds.problem(value)
        if why is not None:
            yield path, value, why


def whole(value: Any, key: str, least: int = 1, most: int | None = None, *, allow: tuple = ()) -> int:
    """``value`` as an int in ``[least, most]`` (or one of ``allow``), else a one-line
    :class:`OptionError` naming ``key`` (a command's own option, checked against what it is used for)."""
    if value in allow and not isinstance(value, bool):
        return value
    ok = isinstance(value, int) and not isinstance(value, bool)
    if not ok or value < least or (most is not None and value > most):
        span = f"[{least}, {most}]" if most is not None else f"≥ {least}"
        extra = f" (or {', '.join(map(str, allow))})" if allow else ""
        raise OptionError(f"{key} must be a whole number {span}{extra}, got {value!r}")
    return int(value)


def check_options(config: Any, where: str | None = None) -> None:
    """Refuse (:class:`OptionError`, one line) the first value of ``config`` outside its bounds.

    ``where``: the config's source for the message (``"checkpoint runs/a/last.ckpt"``); ``None`` for
    the command line, whose keys are named as the user types them (``module.lr=-1``)."""
    for path, value, why in option_problems(config):
        shown = repr(value) if isinstance(value, str) else value
        if where is None:
            raise OptionError(f"{path} must be {why}, got {shown} ({path}=...)")
        raise OptionError(
            f"{where}: {path} = {shown} is out of bounds (must be {why}); the file is damaged or was edited"
        )


__all__ = ["BOUNDS", "OptionError", "Real", "Whole", "check_options", "option_problems", "whole"]
