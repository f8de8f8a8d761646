"""``posediff export ckpt_path=CKPT format=onnx|torchscript|exported_program out=DIR``: a checkpoint's
graphs (:func:`posediff.models.export.export_module`), written to ``<out>.partial`` and renamed.

The step count the sampler graph unrolls is settled (:func:`posediff.models.export.unrolled_steps`:
``num_steps``, else the checkpoint's sampler's, else the default; above ``max_unrolled`` refused) and
printed before the export starts. A write that fails (a full disk) is one line naming the folder, and
the unfinished ``.partial`` folder is removed: nothing is left in ``out``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..._io import OutputFolderError, check_output_dir, make_output_dir, remove_own_dir, replace_dir
from ...models import PoseDiffusionModule, load_checkpoint
from ...models.export import FORMATS, ExportError, ExportWriteError, export_module, unrolled_steps
from ...options import whole
from ..errors import InputError, user_input
from ..runs import test_data

COMMAND = "posediff export"


def run(cfg: DictConfig) -> int:
    with user_input():
        module, fmt, out, example, steps, source = what_to_export(cfg)
    why = {"num_steps": f"num_steps={steps}", "sampler": "the checkpoint's sampler's own count",
           "default": "the default; the checkpoint's sampler sets none"}[source]  # fmt: skip
    print(f"{COMMAND}: unrolling {steps} sampling step{'s' * (steps != 1)} into the {fmt} sampler graph "
          f"({why}); num_steps=N changes it", flush=True)  # fmt: skip
    partial = out.with_name(out.name + ".partial")
    remove_own_dir(partial, COMMAND)  # refuses (one line) a .partial folder posediff did not make
    size = int(((module.config or {}).get("data") or {}).get("image_size") or 0)
    try:
        make_output_dir(partial, COMMAND)
        files = export_module(
            module, partial, fmt, example=example, num_steps=steps, num_samples=int(cfg.num_samples),
            info={"ckpt_path": str(cfg.ckpt_path), "image_size": size or None}, max_unrolled=cfg.get("max_unrolled"),
        )  # fmt: skip
        replace_dir(partial, out, COMMAND)
    except (ExportError, OutputFolderError):
        remove_own_dir(partial, COMMAND)
        raise
    except OSError as e:  # ExportWriteError (a graph or the JSON), or the folder / marker (a full disk)
        remove_own_dir(partial, COMMAND)
        msg = str(e) if isinstance(e, ExportWriteError) else (
            f"cannot write in {partial}: {e.strerror or e}; free space there or choose another out="
        )  # fmt: skip
        raise InputError(f"out={out}: {msg}") from None
    except BaseException:
        remove_own_dir(partial, COMMAND)
        raise
    for name, path in files.items():
        print(f"{name}: {out / path.name}")
    return 0


def what_to_export(cfg: DictConfig) -> tuple[PoseDiffusionModule, str, Path, torch.Tensor, int, str]:
    """The options checked, then the model, format, output folder, an example input and the step
    count the sampler graph unrolls (with where that count came from)."""
    fmt = str(cfg.format)
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; choose one of: {', '.join(FORMATS)}")
    whole(cfg.num_samples, "num_samples", 2)
    if cfg.num_steps is not None:
        whole(cfg.num_steps, "num_steps")
    max_unrolled = cfg.get("max_unrolled")
    if max_unrolled is not None:
        whole(max_unrolled, "max_unrolled")
    out = Path(str(cfg.out)) if cfg.out else Path(HydraConfig.get().runtime.output_dir) / fmt
    if out.exists() and not cfg.overwrite:
        raise ExportError(f"out={out} already exists; give a new folder or overwrite=true")
    check_output_dir(out, COMMAND, replace=True, key="out")  # only a folder posediff made is replaced
    module: Any = load_checkpoint(cfg.ckpt_path)
    if not isinstance(module, PoseDiffusionModule) or not hasattr(module.sampler, "step"):
        raise ExportError(
            f"checkpoint {cfg.ckpt_path} is a {type(module).__name__} (no diffusion sampler): "
            "posediff export writes diffusion models only"
        )
    config = module.config or {}
    size = int((config.get("data") or {}).get("image_size") or 0)
    if module.cond_key == "image" and size:
        example = torch.zeros(1, 3, size, size)
    else:  # a condition of the run's own test data (the toys)
        example = next(iter(test_data(OmegaConf.create(config)).test_dataloader()))[module.cond_key][:1]
    num_steps = None if cfg.num_steps is None else int(cfg.num_steps)
    steps, source = unrolled_steps(module.sampler, fmt, num_steps, max_unrolled)
    return module, fmt, out, example, steps, source
