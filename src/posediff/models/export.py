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

The loop is unrolled: every step is a copy of the network in the graph, so the export time grows with
the step count (faster than linearly for ONNX, whose graph optimiser dominates). The default is the
checkpoint's sampler's own ``num_steps``, else :data:`DEFAULT_NUM_STEPS`; counts above
:data:`MAX_UNROLLED` are refused unless ``max_unrolled`` is raised (:func:`unrolled_steps`).

Each graph is serialised in memory and written from Python to a temporary name in the destination
folder, then renamed (``posediff._io.atomic_write_bytes``): a full disk is an :class:`ExportWriteError`
naming the folder, never a truncated file (PyTorch's own file writers abort the process from C++ when
a write fails).

Loading (:func:`load_exported`) trusts nothing in the folder: every file the JSON names must be a plain
file name inside the folder with the format's suffix, and only ONNX (through ONNX Runtime) is loaded
by default — ``torch.export.load`` and ``torch.jit.load`` run code a tampered file holds, so those
formats need ``trust=True`` (only for files you made yourself).
"""

from __future__ import annotations

import copy
import io
import json
import os
import re
import types
import zipfile
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .. import __version__
from .._io import atomic_write_bytes
from ..config.allowlist import check_config
from .diffusion import PoseDiffusionModule

FORMATS = ("onnx", "torchscript", "exported_program")
META_FILE = "posediff_export.json"
GRAPHS = ("encoder", "denoiser", "sampler")
_SUFFIX = {"onnx": ".onnx", "torchscript": ".pt", "exported_program": ".pt2"}

#: Steps unrolled into the ``sampler`` graph when neither ``num_steps`` nor the checkpoint's sampler
#: gives a count. Measured on the toy SO(3) checkpoint (2 CPU cores, the whole ``posediff export``):
#: ONNX 45 s at 5 steps, 82 s at 10, 4 min at 20; ExportedProgram 9 s at 5, 15 s at 10; TorchScript
#: under a second (6 s at 100).
DEFAULT_NUM_STEPS = 5

#: The most steps each format unrolls unless ``max_unrolled`` says otherwise: ONNX's exporter time grows
#: faster than the step count (every schedule level of the toy, 100 steps, ran for over 14 minutes);
#: ExportedProgram grows about linearly (~1 s a step); TorchScript traces 100 steps in ~6 s (no bound).
MAX_UNROLLED: dict[str, int | None] = {"onnx": 20, "exported_program": 50, "torchscript": None}


class ExportError(ValueError):
    """A model or an option that cannot be exported (one line)."""


class ExportWriteError(OSError):
    """An exported file that could not be written (a full disk, a quota, a read-only folder): one line
    naming the folder and the file; nothing half-written is left under the file's name."""


class ExportedFilesError(ValueError):
    """An export folder that :func:`load_exported` refuses to load (one line): no or a malformed
    ``posediff_export.json``, a file entry that is not a plain file name inside the folder with the
    format's suffix, a format whose loader runs code from the file without ``trust=True``, or a
    ``.pt2`` archive holding pickled, compiled or unknown parts."""


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
    """The sampler's own grid (``Sampler.sigma_grid``: noise levels, or a flow sampler's times)."""
    sig_t, sig_p = sampler.sigma_grid(num_steps)
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


def _serialize(
    model: nn.Module, args: tuple[Tensor, ...], fmt: str, names: list[str], dynamic: dict
) -> tuple[bytes, bool]:
    """One graph's file contents, made in memory (no exporter writes to disk), and whether its batch /
    hypothesis dimensions are dynamic."""
    import warnings

    model.eval()
    buffer = io.BytesIO()
    if fmt == "torchscript":
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the tracer's notes on shape checks it turns into constants
            traced = torch.jit.trace(model, args, check_trace=False)
        return bytes(traced.save_to_buffer()), False
    if fmt == "exported_program":
        try:
            ep = torch.export.export(model, args, dynamic_shapes=dynamic)
            dyn = True
        except Exception:  # noqa: BLE001 - an exporter that cannot keep a dimension dynamic: fixed shapes
            ep = torch.export.export(model, args)
            dyn = False
        torch.export.save(ep, buffer)
        return buffer.getvalue(), dyn
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            prog = torch.onnx.export(model, args, dynamo=True, input_names=names, dynamic_shapes=dynamic,
                                     verbose=False)  # fmt: skip
            dyn = True
        except Exception:  # noqa: BLE001
            prog = torch.onnx.export(model, args, dynamo=True, input_names=names, verbose=False)
            dyn = False
    try:
        return prog.model_proto.SerializeToString(), dyn
    except ValueError as e:  # protobuf's 2 GB limit for one message (the weights inline)
        raise ExportError(
            f"the {type(model).__name__} graph is too large for one ONNX file ({e}); "
            "export format=exported_program or format=torchscript"
        ) from e


def _write(path: Path, data: bytes) -> Path:
    """``data`` to ``path`` through a temporary name in its folder and a rename; a failed write is an
    :class:`ExportWriteError` naming the folder (the temporary file removed)."""

    try:
        return atomic_write_bytes(path, data)
    except OSError as e:
        why = e.strerror or str(e) or type(e).__name__
        raise ExportWriteError(
            f"cannot write {path.name} ({len(data) / 1e6:.1f} MB) in {path.parent}: {why}; "
            "free space there or choose another out="
        ) from e


def unrolled_steps(
    sampler: Any, fmt: str, num_steps: int | None = None, max_unrolled: int | None = None
) -> tuple[int, str]:
    """``(steps, where from)``: the steps the ``sampler`` graph unrolls — ``num_steps``, else the
    sampler's own ``num_steps``, else :data:`DEFAULT_NUM_STEPS` (at most the schedule's levels) — and
    ``"num_steps"``, ``"sampler"`` or ``"default"``. Refuses (:class:`ExportError`) a count outside the
    schedule's levels, and one above ``max_unrolled`` (default :data:`MAX_UNROLLED` of ``fmt``), saying
    how to export it anyway."""
    levels = sampler.diffusion.schedule.num_levels
    if num_steps is not None:
        steps, source = num_steps, "num_steps"
    elif getattr(sampler, "num_steps", None):
        steps, source = sampler.num_steps, "sampler"
    else:
        steps, source = min(DEFAULT_NUM_STEPS, levels), "default"
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= levels:
        raise ExportError(f"num_steps must be in [1, {levels}] (the schedule's levels), got {steps!r}")
    bound = MAX_UNROLLED.get(fmt) if max_unrolled is None else max_unrolled
    if isinstance(bound, bool) or (bound is not None and (not isinstance(bound, int) or bound < 1)):
        raise ExportError(f"max_unrolled must be a whole number ≥ 1, got {max_unrolled!r}")
    if bound is not None and steps > bound:
        what = f"num_steps={steps}" if source == "num_steps" else f"the checkpoint's sampler's {steps} steps"
        raise ExportError(
            f"{what} would unroll into one {fmt} graph, above max_unrolled={bound} ({fmt} export time grows "
            f"with every unrolled step; 100 took over 14 min for ONNX): give num_steps≤{bound}, or "
            f"max_unrolled={steps} to export all {steps} anyway"
        )
    return int(steps), source


def export_module(
    module: Any,
    out: str | Path,
    fmt: str,
    *,
    example: Tensor,
    num_steps: int | None = None,
    num_samples: int = 16,
    info: dict[str, Any] | None = None,
    max_unrolled: int | None = None,
) -> dict[str, Path]:
    """Export ``module`` (a :class:`~posediff.models.PoseDiffusionModule`) in ``fmt`` into the folder
    ``out`` (module docstring). ``example``: one input batch for the encoder (e.g. ``(1, 3, S, S)``);
    ``num_steps``: the loop's steps (default the sampler's, else :data:`DEFAULT_NUM_STEPS`; above
    ``max_unrolled``, default :data:`MAX_UNROLLED`, refused — :func:`unrolled_steps`); ``num_samples``:
    the example's hypotheses per input. Each file is written whole or not at all; a failed write raises
    :class:`ExportWriteError`. Returns name → path."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; choose one of: {', '.join(FORMATS)}")
    sampler = getattr(module, "sampler", None)
    if not isinstance(module, PoseDiffusionModule) or not hasattr(sampler, "step"):
        raise ExportError(
            f"{type(module).__name__} is not a diffusion model with a sampler; nothing to export"
        )
    if getattr(sampler, "fresh_prior", False) is True and getattr(sampler, "objective", "dsm") == "flow":
        raise ExportError(
            f"{sampler.name} fresh_prior=true draws a prior pose every step, which the exported loop cannot "
            "take as an input: export with sampler.fresh_prior=false"
        )
    steps, _ = unrolled_steps(sampler, fmt, num_steps, max_unrolled)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ExportWriteError(f"cannot make the export folder {out}: {e.strerror or e}") from e
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
        data, dynamic[name] = _serialize(model, args, fmt, names, dyn)
        files[name] = _write(out / f"{name}{_SUFFIX[fmt]}", data)
        del data

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
    files["meta"] = _write(out / META_FILE, (json.dumps(meta, indent=2) + "\n").encode("utf-8"))
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

    check_config({"diffusion": config}, where="export diffusion_config")
    diffusion = instantiate(config)
    x = diffusion.prior((batch, num_samples), generator=generator, dtype=dtype)
    noise = torch.zeros((int(meta["num_steps"]), batch, num_samples, int(meta["dim"])), dtype=dtype)
    for j, draws in enumerate(meta["noise_steps"]):
        if draws:
            noise[j] = torch.randn((batch, num_samples, int(meta["dim"])), generator=generator, dtype=dtype)
    return x, noise


#: Why a format's loader is not safe for a file someone else made (facts checked on PyTorch 2.14).
_UNSAFE_LOADER = {
    "exported_program": "torch.export.load unpickles parts of a .pt2 (weights or constants marked "
    "pickled, its sample inputs), evaluates its shape expressions with sympy and runs its guard code",
    "torchscript": "torch.jit.load runs the TorchScript code a .pt holds (its __setstate__), which can "
    "read and overwrite files",
}

#: Every member a ``torch.export.save`` archive of posediff's graphs holds, below its root folder; a
#: .pt2 with anything else (AOTInductor's compiled libraries, pickled legacy weights, …) is refused.
_PT2_MEMBER = re.compile(
    r"(archive_format|archive_version|byteorder|\.data/version|\.data/serialization_id"
    r"|models/\w+\.json|data/sample_inputs/\w+\.pt|extra/[\w.-]+"
    r"|data/weights/\w+_weights_config\.json|data/weights/weight_\d+"
    r"|data/constants/\w+_constants_config\.json|data/constants/tensor_\d+)"
)


def _confined(folder: Path, key: str, entry: Any, suffix: str) -> Path:
    """The file the JSON's ``files.<key>`` names, resolved: a plain file name (no folder, no ``..``,
    not absolute) of a regular file with ``suffix`` whose real path (symbolic links followed) lies in
    ``folder`` (resolved); :class:`ExportedFilesError` otherwise."""
    where = f"files.{key}={entry!r} in {folder / META_FILE}"
    if not isinstance(entry, str) or not entry:
        raise ExportedFilesError(
            f"{where}: not a file name; an export names its own files, e.g. {key}{suffix}"
        )
    if (
        entry in (".", "..")
        or "/" in entry
        or "\\" in entry
        or os.path.isabs(entry)
        or Path(entry).name != entry
    ):
        raise ExportedFilesError(
            f"{where}: not a plain file name in the export folder (a path, '..' or an absolute path); refused"
        )
    if not entry.endswith(suffix):
        raise ExportedFilesError(f"{where}: not a {suffix} file, which this format's files are; refused")
    real = (folder / entry).resolve()
    if not real.is_relative_to(folder):
        raise ExportedFilesError(f"{where}: leads outside the export folder (to {real}); refused")
    if not real.is_file():
        raise ExportedFilesError(f"{where}: no such file in {folder}; export again (posediff export)")
    return real


def _check_pt2(path: Path) -> None:
    """Refuse (:class:`ExportedFilesError`) a ``.pt2`` whose loading would unpickle or run anything a
    file holds that posediff's exports never hold: members outside :data:`_PT2_MEMBER` (AOTInductor
    libraries, legacy pickled weights), weights or constants marked pickled or of non-tensor kinds
    (custom and opaque objects are unpickled), and sample inputs ``torch.load(weights_only=True)``
    refuses (``torch.export.load`` would retry them with ``weights_only=False``)."""
    bad = f"{path.name} is not a plain torch.export archive of tensors"
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
            roots = {n.split("/", 1)[0] for n in names}
            if len(roots) != 1 or not names:
                raise ExportedFilesError(f"{bad} (no single root folder); refused")
            root = roots.pop() + "/"
            for n in names:
                if not _PT2_MEMBER.fullmatch(n[len(root) :]):
                    raise ExportedFilesError(f"{bad}: it holds {n!r}, which posediff never writes; refused")
            for n in names:
                rel = n[len(root) :]
                if rel.endswith(("_weights_config.json", "_constants_config.json")):
                    prefix = "weight_" if "/weights/" in rel else "tensor_"
                    config = json.loads(z.read(n)).get("config", {})
                    for fqn, entry in config.items():
                        if entry.get("use_pickle") or not re.fullmatch(
                            prefix + r"\d+", str(entry.get("path_name"))
                        ):
                            raise ExportedFilesError(
                                f"{bad}: {rel} marks {fqn!r} as pickled or not a tensor; refused (loading "
                                "it would unpickle what the file holds)"
                            )
                elif rel.startswith("data/sample_inputs/"):
                    try:
                        torch.load(io.BytesIO(z.read(n)), weights_only=True)
                    except Exception as e:  # noqa: BLE001 - anything weights_only refuses is refused
                        raise ExportedFilesError(
                            f"{bad}: its sample inputs {rel} are not plain tensors ({type(e).__name__}); refused"
                        ) from e
    except (zipfile.BadZipFile, json.JSONDecodeError, AttributeError, OSError) as e:
        raise ExportedFilesError(f"{bad} ({type(e).__name__}: {e}); refused") from e


def load_exported(folder: str | Path, *, trust: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(meta, runners)``: the export's JSON and one callable per graph (``encoder(input)``,
    ``denoiser(x, sigma, cond)``, ``sampler(cond, x_init, noise)``), over torch tensors.

    Nothing the folder holds is trusted: each ``files`` entry must be a plain file name of a file inside
    ``folder`` with the format's suffix (:func:`_confined`). ONNX is loaded through ONNX Runtime, which
    runs only the ONNX operators of the graph (and refuses external weights outside the folder).
    TorchScript and ExportedProgram loaders run code a tampered file holds (:data:`_UNSAFE_LOADER`), so
    those formats are refused unless ``trust=True`` — only for files you made yourself; even then a
    ``.pt2`` holding pickled or compiled parts is refused (:func:`_check_pt2`). Every refusal is an
    :class:`ExportedFilesError` (one line)."""
    folder = Path(folder).resolve()
    meta_path = folder / META_FILE
    if not meta_path.is_file():
        raise ExportedFilesError(
            f"no {META_FILE} in {folder}: not a posediff export folder (posediff export writes one)"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ExportedFilesError(
            f"{meta_path} is not valid JSON ({e}); export again (posediff export)"
        ) from e
    fmt = meta.get("format") if isinstance(meta, dict) else None
    if fmt not in FORMATS:
        raise ExportedFilesError(
            f"{meta_path}: unknown format {fmt!r}; an export is one of: {', '.join(FORMATS)}"
        )
    files = meta.get("files")
    if not isinstance(files, dict) or set(files) != set(GRAPHS):
        raise ExportedFilesError(
            f"{meta_path}: 'files' must name exactly the graphs {', '.join(GRAPHS)}, got "
            f"{sorted(files) if isinstance(files, dict) else files!r}"
        )
    paths = {name: _confined(folder, name, files[name], _SUFFIX[fmt]) for name in GRAPHS}
    if fmt in _UNSAFE_LOADER and not trust:
        raise ExportedFilesError(
            f"{folder} is a format={fmt} export, and {_UNSAFE_LOADER[fmt]}: load_exported(folder, "
            "trust=True) loads it — only for files you made yourself — or use a format=onnx export "
            "(ONNX Runtime runs no such code)"
        )
    runners: dict[str, Any] = {}
    for name, path in paths.items():
        if fmt == "torchscript":
            runners[name] = torch.jit.load(str(path))
        elif fmt == "exported_program":
            _check_pt2(path)
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
    "DEFAULT_NUM_STEPS",
    "FORMATS",
    "GRAPHS",
    "MAX_UNROLLED",
    "META_FILE",
    "ConditionEncoder",
    "DenoiserStep",
    "ExportError",
    "ExportWriteError",
    "ExportedFilesError",
    "SamplingLoop",
    "draw_from_meta",
    "draw_inputs",
    "export_module",
    "load_exported",
    "noise_steps",
    "unrolled_steps",
]
