"""Export a trained model to run elsewhere: ONNX, TorchScript or ``torch.export`` (ExportedProgram).

:func:`export_module` writes three graphs and one JSON file into a folder:

* ``encoder`` — the input (e.g. an image ``(B, 3, S, S)``) → the condition ``(B, C)`` the denoiser
  reads (the feature, with the anchor pose packed behind it for anchored models); run once per input;
* ``denoiser`` — one network evaluation: noisy poses ``x (B, N, n, n)``, levels ``sigma (B, N)`` and
  the condition → the raw output ``(B, N, dim)`` (a score or a noise estimate, ``diffusion.output``);
* ``sampler`` — the whole sampling loop for a fixed number of steps: ``(cond (B, C), x_init (B, N, n,
  n), noise (T, B, N, dim)) → x (B, N, n, n)``; ``x_init`` is a draw from the prior and ``noise[j]``
  the standard-normal draw step ``j`` uses (steps that draw none ignore theirs), so the randomness
  stays outside the graph and every runtime gives the same poses for the same inputs;
* ``posediff_export.json`` — the group, the step count, the levels σ, the sampler and diffusion
  settings, the prior, the input and output names and shapes, and which steps read noise.

Batch size ``B`` and hypotheses ``N`` are the example's (``num_samples``, batch 1) for TorchScript
(traced) and dynamic for ONNX and ExportedProgram where the exporter allows it (the JSON says which).
:func:`draw_inputs` (from a sampler) and :func:`draw_from_meta` (from the JSON alone) draw ``x_init``
and ``noise`` as :meth:`posediff.diffusion.Sampler.sample` would — the same values for the same
generator; any other source of the same distributions works as well.
"""

from __future__ import annotations

import copy
import json
import types
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

FORMATS = ("onnx", "torchscript", "exported_program")
META_FILE = "posediff_export.json"
_SUFFIX = {"onnx": ".onnx", "torchscript": ".pt", "exported_program": ".pt2"}


class ExportError(ValueError):
    """A model or an option that cannot be exported (one line)."""


class _Wrapper(nn.Module):
    """Holds a trained module's networks as its own children (their parameters are the graph's) and
    the LightningModule itself out of sight of the exporters (a Lightning module outside a Trainer
    raises on some attribute look-ups that tracing makes)."""

    def __init__(self, module: Any) -> None:
        super().__init__()
        self.encoder, self.denoiser = module.encoder, module.denoiser
        object.__setattr__(self, "_module", module)


class ConditionEncoder(_Wrapper):
    """``input → condition``: :meth:`PoseDiffusionModule.encode`."""

    def forward(self, cond: Tensor) -> Tensor:
        return self._module.encode(cond)


class DenoiserStep(_Wrapper):
    """``(x, sigma, cond) → raw output``: :meth:`PoseDiffusionModule.forward`."""

    def forward(self, x: Tensor, sigma: Tensor, cond: Tensor) -> Tensor:
        return self._module.forward(x, sigma, cond)


def _levels(sampler: Any, num_steps: int) -> tuple[list[float], list[float]]:
    sched = sampler.diffusion.schedule
    levels = sched.timesteps(num_steps)
    sig_t = sched.sigma(levels, dtype=torch.float64)
    sig_p = sampler._next_sigmas(levels, sig_t)
    return [float(v) for v in sig_t], [float(v) for v in sig_p]


class SamplingLoop(_Wrapper):
    """The sampler's loop for ``num_steps`` steps with the randomness as inputs (module docstring):
    each step is the sampler's own :meth:`~posediff.diffusion.Sampler.step`, its noise draw replaced by
    ``noise[j]``."""

    def __init__(self, module: Any, sampler: Any, num_steps: int) -> None:
        super().__init__(module)
        self.sig_t, self.sig_p = _levels(sampler, num_steps)
        s = copy.copy(sampler)
        s.noise = types.MethodType(lambda self, x, generator: generator.to(x.dtype), s)  # the given draw
        self._sampler = s

    def forward(self, cond: Tensor, x_init: Tensor, noise: Tensor) -> Tensor:
        x = x_init
        for j, (st, sp) in enumerate(zip(self.sig_t, self.sig_p, strict=True)):
            x = self._sampler.step(self._module.forward, x, st, sp, cond, noise[j])
        return x


def noise_steps(sampler: Any, num_steps: int) -> list[bool]:
    """Which steps draw noise (found by running one step of each level on a tiny input)."""
    sig_t, sig_p = _levels(sampler, num_steps)
    g = sampler.group
    out = []
    for st, sp in zip(sig_t, sig_p, strict=True):
        drew = []
        s = copy.copy(sampler)

        def noise(self: Any, x: Tensor, generator: Any, drew: list = drew) -> Tensor:
            drew.append(True)
            return torch.zeros((*x.shape[:-2], g.dim), dtype=x.dtype)

        s.noise = types.MethodType(noise, s)
        x = g.identity((1, 1), dtype=torch.float64)
        s.step(
            lambda x, sigma, cond: torch.zeros((*x.shape[:-2], g.dim), dtype=x.dtype), x, st, sp, None, None
        )
        out.append(bool(drew))
    return out


def draw_inputs(
    sampler: Any, num_steps: int, batch: int, num_samples: int, *, generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(x_init (B, N, n, n), noise (T, B, N, dim))`` as :meth:`Sampler.sample` draws them, in its order
    (the prior, then one draw for each step that draws noise; zeros for the others)."""
    x = sampler.diffusion.prior((batch, num_samples), generator=generator, dtype=dtype)
    dim = sampler.group.dim
    noise = torch.zeros((num_steps, batch, num_samples, dim), dtype=dtype)
    for j, draws in enumerate(noise_steps(sampler, num_steps)):
        if draws:
            noise[j] = torch.randn((batch, num_samples, dim), generator=generator, dtype=dtype)
    return x, noise


def _example_shapes(module: Any, example: Tensor, num_samples: int, num_steps: int) -> dict[str, tuple]:
    n, dim = int(module.group.matrix_dim), int(module.group.dim)
    with torch.no_grad():
        cond = module.encode(example)
    B = int(example.shape[0])
    return {"input": tuple(example.shape), "cond": tuple(cond.shape), "x": (B, num_samples, n, n),
            "sigma": (B, num_samples), "out": (B, num_samples, dim), "noise": (num_steps, B, num_samples, dim)}  # fmt: skip


def _save(
    model: nn.Module, args: tuple[Tensor, ...], path: Path, fmt: str, names: list[str], dynamic: dict
) -> bool:
    """Write one graph; returns whether its batch / hypothesis dimensions are dynamic."""
    import warnings

    model.eval()
    if fmt == "torchscript":
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the tracer's notes on shape checks it turns into constants
            traced = torch.jit.trace(model, args, check_trace=False)
        traced.save(str(path))
        return False
    if fmt == "exported_program":
        try:
            ep = torch.export.export(model, args, dynamic_shapes=dynamic)
            dyn = True
        except Exception:  # noqa: BLE001 - an exporter that cannot keep a dimension dynamic: fixed shapes
            ep = torch.export.export(model, args)
            dyn = False
        torch.export.save(ep, str(path))
        return dyn
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            prog = torch.onnx.export(model, args, dynamo=True, input_names=names, dynamic_shapes=dynamic,
                                     verbose=False)  # fmt: skip
            dyn = True
        except Exception:  # noqa: BLE001
            prog = torch.onnx.export(model, args, dynamo=True, input_names=names, verbose=False)
            dyn = False
    prog.save(str(path))
    return dyn


def export_module(
    module: Any,
    out: str | Path,
    fmt: str,
    *,
    example: Tensor,
    num_steps: int | None = None,
    num_samples: int = 16,
    info: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Export ``module`` (a :class:`~posediff.module.PoseDiffusionModule`) in ``fmt`` into the folder
    ``out`` (module docstring). ``example``: one input batch for the encoder (e.g. ``(1, 3, S, S)``);
    ``num_steps``: the loop's steps (default the sampler's, else every level); ``num_samples``: the
    example's hypotheses per input. Returns name → path."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; choose one of: {', '.join(FORMATS)}")
    sampler = getattr(module, "sampler", None)
    if sampler is None or not hasattr(sampler, "step") or getattr(module, "estimator", None) is not None:
        raise ExportError(
            f"{type(module).__name__} is not a diffusion model with a sampler; nothing to export"
        )
    levels = sampler.diffusion.schedule.num_levels
    steps = int(num_steps if num_steps is not None else (sampler.num_steps or levels))
    if not 1 <= steps <= levels:
        raise ExportError(f"num_steps must be in [1, {levels}] (the schedule's levels), got {steps}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    module = module.eval()
    if fmt != "torchscript" and int(example.shape[0]) == 1:  # a size-1 dimension cannot be exported dynamic
        example = torch.cat([example, example])
    shapes = _example_shapes(module, example, num_samples, steps)
    with torch.no_grad():
        cond = module.encode(example)
    g = torch.Generator().manual_seed(0)
    x_init, noise = draw_inputs(
        sampler, steps, int(example.shape[0]), num_samples, generator=g, dtype=cond.dtype
    )
    sig_t, sig_next = _levels(sampler, steps)
    sigma = torch.full(shapes["sigma"], sig_t[0], dtype=cond.dtype)
    batch, hyp = torch.export.Dim("batch", min=1, max=4096), torch.export.Dim("hypotheses", min=2, max=65536)
    graphs = {
        "encoder": (ConditionEncoder(module), (example,), ["input"], {"cond": {0: batch}}),
        "denoiser": (DenoiserStep(module), (x_init, sigma, cond), ["x", "sigma", "cond"],
                     {"x": {0: batch, 1: hyp}, "sigma": {0: batch, 1: hyp}, "cond": {0: batch}}),
        "sampler": (SamplingLoop(module, sampler, steps), (cond, x_init, noise), ["cond", "x_init", "noise"],
                    {"cond": {0: batch}, "x_init": {0: batch, 1: hyp}, "noise": {1: batch, 2: hyp}}),
    }  # fmt: skip
    files: dict[str, Path] = {}
    dynamic: dict[str, bool] = {}
    for name, (model, args, names, dyn) in graphs.items():
        path = out / f"{name}{_SUFFIX[fmt]}"
        dynamic[name] = _save(model, args, path, fmt, names, dyn)
        files[name] = path
    from . import __version__

    meta = {
        "format": fmt,
        "posediff": __version__,
        "files": {k: v.name for k, v in files.items()},
        "group": module.group.name,
        "matrix_dim": int(module.group.matrix_dim),
        "dim": int(module.group.dim),
        "num_steps": steps,
        "sigma_t": sig_t,
        "sigma_next": sig_next,
        "noise_steps": noise_steps(sampler, steps),
        "sampler": {"name": getattr(sampler, "name", type(sampler).__name__),
                    **{k: v for k, v in vars(sampler).items() if isinstance(v, (int, float, str, bool))}},
        "diffusion": sampler.diffusion.describe(),
        "cond_key": getattr(module, "cond_key", "cond"),
        # the diffusion's config (allow-listed classes only), so that draw_from_meta can draw the prior
        "diffusion_config": (getattr(module, "config", None) or {}).get("diffusion"),
        "example_shapes": {k: list(v) for k, v in shapes.items()},
        "dynamic": dynamic,
        "inputs": {"encoder": ["input"], "denoiser": ["x", "sigma", "cond"], "sampler": ["cond", "x_init", "noise"]},
        **(info or {}),
    }  # fmt: skip
    from ._io import atomic_write_text

    files["meta"] = atomic_write_text(out / META_FILE, json.dumps(meta, indent=2) + "\n")
    return files


def draw_from_meta(
    meta: dict[str, Any], batch: int, num_samples: int, *, generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """:func:`draw_inputs` from an export's JSON alone: the diffusion is rebuilt from its stored config
    (checked against posediff's allow-list first, as a checkpoint's), the prior drawn, then one
    standard-normal draw for each step the JSON marks — the same values as ``module.sample`` with the
    same generator."""
    config = meta.get("diffusion_config")
    if not isinstance(config, dict):
        raise ExportError("this export has no diffusion config (made from a module without a run config)")
    from hydra.utils import instantiate

    from .allowlist import check_config

    check_config({"diffusion": config}, where="export diffusion_config")
    diffusion = instantiate(config)
    x = diffusion.prior((batch, num_samples), generator=generator, dtype=dtype)
    noise = torch.zeros((int(meta["num_steps"]), batch, num_samples, int(meta["dim"])), dtype=dtype)
    for j, draws in enumerate(meta["noise_steps"]):
        if draws:
            noise[j] = torch.randn((batch, num_samples, int(meta["dim"])), generator=generator, dtype=dtype)
    return x, noise


def load_exported(folder: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(meta, runners)``: the export's JSON and one callable per graph (``encoder(input)``,
    ``denoiser(x, sigma, cond)``, ``sampler(cond, x_init, noise)``), over torch tensors, for any format
    (ONNX through ONNX Runtime)."""
    folder = Path(folder)
    meta = json.loads((folder / META_FILE).read_text(encoding="utf-8"))
    runners: dict[str, Any] = {}
    for name, file in meta["files"].items():
        path = folder / file
        if meta["format"] == "torchscript":
            runners[name] = torch.jit.load(str(path))
        elif meta["format"] == "exported_program":
            runners[name] = torch.export.load(str(path)).module()
        else:
            import onnxruntime as ort

            sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
            inputs = [i.name for i in sess.get_inputs()]

            def run(*args: Tensor, sess: Any = sess, inputs: list[str] = inputs) -> Tensor:
                feed = {k: a.detach().cpu().numpy() for k, a in zip(inputs, args, strict=True)}
                return torch.from_numpy(sess.run(None, feed)[0])

            runners[name] = run
    return meta, runners


__all__ = [
    "FORMATS",
    "META_FILE",
    "ConditionEncoder",
    "DenoiserStep",
    "ExportError",
    "SamplingLoop",
    "draw_from_meta",
    "draw_inputs",
    "export_module",
    "load_exported",
    "noise_steps",
]
