"""The composition root: the only place where objects are built from config and wired together.

Each function here backs one ``posediff`` subcommand; ``posediff.cli`` only parses arguments.
"""

import json
import sys
import time
from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from rich.console import Console
from rich.table import Table

from .evaluation import evaluate_data, write_results
from .evaluation.report import fit_markdown, headline
from .lie import LieGroup
from .testing import LIE_GROUP_CHECKS


def likelihood_options(eval_cfg: Any) -> dict[str, Any]:
    """``eval.log_likelihood`` (null: the data's default, on for SYMSOL) and ``eval.log_likelihood_steps``."""
    flag = eval_cfg.get("log_likelihood")
    if flag is not None and not isinstance(flag, bool):
        raise ValueError(f"eval.log_likelihood must be true, false or null, got {flag!r}")
    # its bounds are posediff.options' (checked with every option before the command runs)
    return {"log_likelihood": flag, "log_likelihood_steps": int(eval_cfg.get("log_likelihood_steps", 50))}


def list_groups() -> int:
    """``posediff groups``: the registered Lie groups and their tensor layouts."""
    table = Table(title="registered Lie groups")
    for col in ("name", "class", "element", "tangent", "order"):
        table.add_column(col)
    for name, cls in sorted(LieGroup.registry.items()):
        order = _tangent_order(cls)
        n = cls.matrix_dim
        table.add_row(
            name, f"{cls.__module__}.{cls.__qualname__}", f"(*b, {n}, {n})", f"(*b, {cls.dim})", order
        )
    Console().print(table)
    return 0


def _tangent_order(cls: type[LieGroup]) -> str:
    """``[ρ(3), φ(3)]``: the runs of translation (ρ) and rotation (φ) components of the tangent."""
    rot = range(cls.dim)[cls.rotation_slice]
    labels = ["φ" if i in rot else "ρ" for i in range(cls.dim)]
    runs: list[list[str | int]] = []
    for lab in labels:
        if runs and runs[-1][0] == lab:
            runs[-1][1] = int(runs[-1][1]) + 1
        else:
            runs.append([lab, 1])
    return "[" + ", ".join(f"{lab}({k})" for lab, k in runs) + "]"


def check_group(cfg: DictConfig) -> int:
    """``posediff check``: run the Lie group contract on ``instantiate(cfg.group)``."""
    group = instantiate(cfg.group)
    if not isinstance(group, LieGroup):
        raise TypeError(f"group config builds {type(group).__name__}, not a posediff LieGroup")
    names = list(cfg.checks) if cfg.checks is not None else list(LIE_GROUP_CHECKS)
    unknown = [n for n in names if n not in LIE_GROUP_CHECKS]
    if unknown:
        print(
            f"posediff check: unknown check(s) {unknown}; available: {', '.join(LIE_GROUP_CHECKS)}",
            file=sys.stderr,
        )
        return 2
    device = torch.device(cfg.device)
    table = Table(title=f"contract of {group!r} on {device}")
    table.add_column("check")
    table.add_column("result")
    failed = 0
    for name in names:
        try:
            LIE_GROUP_CHECKS[name](group, device)
            table.add_row(name, "[green]ok[/green]")
        except Exception as e:  # noqa: BLE001 - every failing check is reported, none aborts the run
            failed += 1
            first = str(e).strip().splitlines()[0] if str(e).strip() else "failed"
            kind = "" if isinstance(e, AssertionError) else f"{type(e).__name__}: "
            table.add_row(name, f"[red]FAIL[/red] {kind}{first}")
    Console().print(table)
    print(f"{group.name}: {len(names) - failed}/{len(names)} checks passed")
    return 1 if failed else 0


def pretrain(cfg: DictConfig) -> int:
    """``posediff pretrain``: ``fit`` with the ``pretrain`` experiment (symmetry-aware regression of the
    :class:`~posediff.nn.PoseEncoder` on posediff's renders), then the encoder's weights to ``cfg.out``
    (atomically) for ``encoder.weights=...``."""
    if not cfg.get("out"):
        print(
            "posediff pretrain: out= is empty; give the file to write the encoder's weights to",
            file=sys.stderr,
        )
        return 2
    return fit(cfg, encoder_out=Path(str(cfg.out)))


def _save_encoder(module: Any, path: Path, cfg: DictConfig, results: dict[str, Any]) -> Path:
    """The encoder's state dict and what made it, as a ``weights_only``-loadable file (temp name, rename)."""
    import io

    from ._io import atomic_write_bytes

    after = next(iter(results.get("after", {}).values()), {})
    res = next(iter(after.values()), {})
    info = {
        "experiment": _experiment_name(),
        "encoder": OmegaConf.to_container(cfg.encoder, resolve=True),
        "data": {"root": str(cfg.data.get("root")), "image_size": int(cfg.data.image_size)},
        "train": results.get("train", {}),
        "spread_deg": {k: float(v.get("spread_deg", float("nan"))) for k, v in res.get("shapes", {}).items()},
    }
    buf = io.BytesIO()
    state = {k: v.detach().cpu().clone() for k, v in module.encoder.state_dict().items()}
    torch.save({"encoder_state_dict": state, "posediff_pretrain": info}, buf)
    return atomic_write_bytes(path, buf.getvalue())


def fit(cfg: DictConfig, *, encoder_out: Path | None = None) -> int:
    """``posediff fit``: train ``cfg.module`` on ``cfg.data`` with ``cfg.trainer``, then evaluate it.

    Writes ``metrics.json`` and ``metrics.md`` (atomically) in the Hydra run folder: the untrained model's metrics
    (``before``), the training loss curve summary and, for every sampler in ``eval.samplers`` and
    every step count in ``eval.num_steps``, per-shape spread / translation error / coverage.
    """
    import lightning as L

    from ._io import atomic_write_json, atomic_write_text
    from .models import PoseModule

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        likelihood = likelihood_options(cfg.eval)  # refused before training, not after it
    except ValueError as e:
        print(f"posediff fit: {e}", file=sys.stderr)
        return 2
    try:
        datamodule = instantiate(cfg.data)
        datamodule.setup("fit")
    except Exception as e:  # noqa: BLE001 - missing / malformed data: one line, not a traceback
        message = _data_error(e)
        if message is None:
            raise
        print(f"posediff fit: {message}", file=sys.stderr)
        return 2
    print(datamodule.describe())
    try:
        module = instantiate(cfg.module)
    except Exception as e:  # noqa: BLE001 - a missing weights file or a bad option: one line
        message = _data_error(e)
        if message is None:
            raise
        print(f"posediff fit: {message}", file=sys.stderr)
        return 2
    if not isinstance(module, PoseModule):
        raise TypeError(f"module config builds {type(module).__name__}, not a PoseModule")
    try:  # every option checked now, not after hours of training
        eval_samplers = _check_fit_options(cfg, module)
    except ValueError as e:
        print(f"posediff fit: {_data_error(e) or e}", file=sys.stderr)
        return 2
    module.config = OmegaConf.to_container(cfg, resolve=True)
    if cfg.ckpt_path is not None:
        from .models import CONFIG_KEY, CheckpointError, check_compatible, read_checkpoint

        try:
            stored_ckpt = read_checkpoint(cfg.ckpt_path)
            check_compatible(
                stored_ckpt[CONFIG_KEY],
                group=module.group.name,
                shapes=list(getattr(datamodule, "shapes", [])) or None,
                where=f"checkpoint {cfg.ckpt_path}",
            )
            _check_same_architecture(stored_ckpt["state_dict"], module, cfg.ckpt_path)
        except CheckpointError as e:
            print(f"posediff fit: cannot resume: {e}", file=sys.stderr)
            return 2
    _lightning_logs_to_stdout()
    callbacks = list(instantiate(cfg.trainer.get("callbacks")) or [])
    if not cfg.trainer.get("enable_progress_bar", True):  # Lightning refuses a bar callback then
        from lightning.pytorch.callbacks import ProgressBar

        callbacks = [c for c in callbacks if not isinstance(c, ProgressBar)]
    if cfg.get("ema") is not None:
        callbacks.append(instantiate(cfg.ema))
    trainer = instantiate(cfg.trainer, callbacks=callbacks)
    stored = datamodule.checkpoint_data()  # e.g. BOP: the training split's translation statistics
    if stored:
        module.config["data"].update(stored)
        for key, value in stored.items():
            print(f"stored with the checkpoint: data.{key} = {value}")
    results: dict[str, Any] = {"experiment": _experiment_name(), "diffusion": module.diffusion.describe()}
    # DDP ranks > 0 re-run this function; they only train (the trainer knows its rank from the launcher)
    if cfg.eval.before and trainer.is_global_zero:
        module.to(trainer.strategy.root_device)
        results["before"] = evaluate_data(
            module,
            datamodule,
            num_samples=int(cfg.eval.get("before_num_samples") or cfg.eval.num_samples),
            num_steps=int(max(cfg.eval.num_steps)),
            seed=int(cfg.eval.seed),
            log_likelihood=False,  # the untrained row: its density is the prior's, whatever the image
        )
        results["before"].pop("estimates", None)
        print(f"before training: {headline(results['before'])}")
    start = time.perf_counter()
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.ckpt_path)
    except SystemExit:  # Lightning exits after a graceful Ctrl-C; report it as the interrupt it was
        if trainer.interrupted:
            last = out_dir / "checkpoints" / "last.ckpt"
            hint = f"resume with ckpt_path={last}" if last.is_file() else "no checkpoint was written yet"
            raise KeyboardInterrupt(f"fit stopped at step {trainer.global_step}; {hint}") from None
        raise
    if not trainer.is_global_zero:
        return 0
    losses = module.loss_history
    results["train"] = {
        "steps": int(trainer.global_step),
        "seconds": time.perf_counter() - start,
        "loss_first": _mean(losses[:50]),
        "loss_last": _mean(losses[-50:]),
    }
    results["after"] = {}
    for name, sampler in eval_samplers.items():
        results["after"][name] = {}
        for steps in cfg.eval.num_steps:
            res = evaluate_data(
                module,
                datamodule,
                num_samples=int(cfg.eval.num_samples),
                num_steps=int(steps),
                sampler=sampler,
                seed=int(cfg.eval.seed),
                **likelihood,
            )
            csv = write_results(res, datamodule, out_dir, f"{name}_{int(steps)}steps")
            if csv is not None:
                print(f"BOP19 estimates: {csv}")
            results["after"][name][str(int(steps))] = res
    json.dumps(results)  # fail here, before writing, if something is not serialisable
    text = fit_markdown(results)
    atomic_write_text(out_dir / "metrics.md", text)
    path = atomic_write_json(out_dir / "metrics.json", results)
    print(text)
    print(f"metrics: {path} (and metrics.md)")
    if encoder_out is not None:
        print(
            f"encoder weights: {_save_encoder(module, encoder_out, cfg, results)} (use: encoder.weights=<that file>)"
        )
    return 0


def _lightning_logs_to_stdout() -> None:
    """Lightning's info lines ("GPU available …") once, on stdout with posediff's own output: its loggers
    also write them to stderr, where only errors belong (one line each)."""
    import logging

    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        log = logging.getLogger(name)
        for h in list(log.handlers):
            if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) is sys.stderr:
                log.removeHandler(h)
        log.propagate = True


def _whole(value: Any, key: str, least: int = 1, most: int | None = None, *, allow: tuple = ()) -> int:
    """``value`` as an int in ``[least, most]`` (or one of ``allow``), else a one-line ``ValueError`` naming ``key``."""
    if value in allow and not isinstance(value, bool):
        return value
    ok = isinstance(value, int) and not isinstance(value, bool)
    if not ok or value < least or (most is not None and value > most):
        span = f"[{least}, {most}]" if most is not None else f"≥ {least}"
        extra = f" (or {', '.join(map(str, allow))})" if allow else ""
        raise ValueError(f"{key} must be a whole number {span}{extra}, got {value!r}")
    return int(value)


def _check_fit_options(cfg: DictConfig, module: Any) -> dict[str, Any]:
    """Refuse bad numeric options before training (one line naming the key); the evaluation
    samplers by name (``None``: the module's own), built now so a bad one fails before training."""
    levels = module.diffusion.schedule.num_levels
    _whole(cfg.eval.num_samples, "eval.num_samples")
    steps = list(cfg.eval.num_steps) if cfg.eval.num_steps is not None else []
    if not steps:
        raise ValueError("eval.num_steps is empty; give step counts, e.g. eval.num_steps=[100]")
    for s in steps:
        _whole(s, "eval.num_steps", 1, levels)
    _whole(cfg.trainer.get("max_steps", -1), "trainer.max_steps", allow=(-1,))
    samplers: dict[str, Any] = {}
    for name, sampler_cfg in (cfg.eval.samplers or {"default": None}).items():
        samplers[name] = instantiate(sampler_cfg)(module.diffusion) if sampler_cfg is not None else None
    return samplers


def _check_same_architecture(stored: dict[str, Any], module: Any, path: Any) -> None:
    """Refuse (one line) resuming a checkpoint whose weights do not fit ``module``'s architecture."""
    from .models import CheckpointError

    have = module.state_dict()
    for key in sorted(set(stored) | set(have)):
        a, b = stored.get(key), have.get(key)
        if a is None or b is None or tuple(a.shape) != tuple(b.shape):
            there = "absent" if a is None else f"{tuple(a.shape)}"
            here = "absent" if b is None else f"{tuple(b.shape)}"
            raise CheckpointError(
                f"checkpoint {path} was trained with another architecture ({key}: {there} in the "
                f"checkpoint, {here} with this config); resume with the settings it was trained with "
                "(posediff fit --cfg job shows yours) or start a new run"
            )


def _data_error(e: BaseException) -> str | None:
    """The one-line message of a data error (missing files, bad values), also when Hydra wrapped it
    in an instantiation error; ``None`` for anything else."""
    while e.__cause__ is not None and not isinstance(e, (FileNotFoundError, ValueError)):
        e = e.__cause__
    if isinstance(e, (FileNotFoundError, ValueError)):
        return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return None


def _experiment_name() -> str:
    try:
        choices = HydraConfig.get().runtime.choices
        return str(choices.get("experiment", "none"))
    except ValueError:
        return "none"


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name} but no CUDA device is available (use device=cpu or auto)")
    return dev


def _checkpoint_run(cfg: DictConfig) -> tuple[Any, DictConfig]:
    """The module of ``cfg.ckpt_path`` and its run config with the command's ``group`` / ``data`` /
    ``sampler`` choices applied (a data mapping without ``_target_`` overrides single keys)."""
    from .models import CONFIG_KEY, check_compatible, module_from_checkpoint, read_checkpoint

    ckpt = read_checkpoint(cfg.ckpt_path)
    config = ckpt[CONFIG_KEY]
    run = OmegaConf.create(config)
    data = cfg.get("data")
    if data:
        d = OmegaConf.to_container(data, resolve=False)
        run.data = d if "_target_" in d else OmegaConf.merge(run.data, d)
    group = None
    if cfg.get("group") is not None:
        from hydra.utils import get_class

        group = str(get_class(cfg.group._target_).name)
    shapes = list(run.data.shapes) if "shapes" in run.data else None
    check_compatible(config, group=group, shapes=shapes, where=f"checkpoint {cfg.ckpt_path}")
    module = module_from_checkpoint(ckpt, cfg.ckpt_path)
    sampler = cfg.get("sampler")
    if sampler:
        s = OmegaConf.to_container(sampler, resolve=True)
        if "_target_" not in s:  # single keys over the stored sampler; null keeps the stored value
            s = {k: v for k, v in s.items() if v is not None}
        run.module.sampler = s if "_target_" in s else OmegaConf.merge(run.module.sampler, s)
    module.sampler = instantiate(run.module.sampler)(module.diffusion)  # bad num_steps: one-line ValueError
    return module, run


def _data(run: DictConfig) -> Any:
    """The test data of a run config (``data.*`` as stored, with any overrides applied); data errors
    as one-line ``ValueError``."""
    try:
        datamodule = instantiate(run.data)
        datamodule.setup("test")
    except Exception as e:  # noqa: BLE001
        message = _data_error(e)
        if message is None:
            raise
        raise ValueError(message) from None
    return datamodule


def evaluate_checkpoint(cfg: DictConfig) -> int:
    """``posediff eval``: metrics of a checkpoint on its (or another) test set; ``metrics.json`` and
    ``metrics.md`` in the run folder. Step counts are a sampler option (``sampler.num_steps``)."""
    from ._io import atomic_write_json, atomic_write_text
    from .evaluation.report import run_table
    from .models import CheckpointError

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        _whole(cfg.num_samples, "num_samples")
        if cfg.max_inputs is not None:
            _whole(cfg.max_inputs, "max_inputs")
        device = _device(str(cfg.device))
        likelihood = likelihood_options(cfg.get("eval") or {})
        module, run = _checkpoint_run(cfg)
        datamodule = _data(run)
    except (CheckpointError, ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"posediff eval: {e}", file=sys.stderr)
        return 2
    print(datamodule.describe())
    module.to(device)
    result = evaluate_data(
        module,
        datamodule,
        num_samples=int(cfg.num_samples),
        num_steps=None,
        seed=int(cfg.seed),
        max_inputs=cfg.max_inputs,
        vsd=bool(cfg.get("vsd", True)),
        **likelihood,
    )
    write_results(result, datamodule, out_dir)
    result.update(
        ckpt_path=str(cfg.ckpt_path),
        device=str(device),
        data=OmegaConf.to_container(run.data, resolve=True),
        sampler_config=OmegaConf.to_container(run.module.sampler, resolve=True),
    )
    atomic_write_json(out_dir / "metrics.json", result)
    table = run_table(result)
    atomic_write_text(out_dir / "metrics.md", table)
    print(table)
    print(f"metrics: {out_dir / 'metrics.json'}")
    if "bop19_csv" in result:
        print(f"BOP19 estimates: {result['bop19_csv']} (for the BOP toolkit's eval_bop19_pose.py)")
    return 0


def score(cfg: DictConfig) -> int:
    """``posediff score csv=PATH data.root=DIR``: BOP19 scores of any results CSV on a BOP dataset's
    test split (:func:`posediff.evaluate_bop.score_estimates`); ``metrics.json`` / ``metrics.md`` in
    the run folder, as ``posediff eval``."""
    import time

    from ._io import atomic_write_json, atomic_write_text
    from .evaluation.bop import check_estimates, score_estimates
    from .evaluation.report import run_table
    from .metrics.bop19 import VSD_DELTAS, read_bop19_csv

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    start = time.perf_counter()
    try:
        csv = Path(str(cfg.csv))
        if not csv.is_file():
            raise FileNotFoundError(
                f"csv={csv}: no such file (a BOP19 results CSV: scene_id,im_id,obj_id,score,R,t,time)"
            )
        rows = read_bop19_csv(csv)
        if not rows:
            raise ValueError(f"{csv}: no estimates in the file")
        if cfg.data is None or "_target_" not in cfg.data:
            raise ValueError("data= must name a BOP data config (data=tless, the default) with data.root=DIR")
        datamodule = instantiate(cfg.data)
        if not hasattr(datamodule, "read_targets"):
            raise ValueError(
                f"data={cfg.data._target_} is not a BOP dataset; posediff score needs one (data=tless)"
            )
        datamodule.read_targets()
        check_estimates(rows, datamodule)
        delta = cfg.vsd_delta
        if delta is None:
            name = datamodule.root.name.lower().replace("_", "").replace("-", "")
            delta = VSD_DELTAS.get(name, 15.0)
        if not float(delta) > 0:
            raise ValueError(f"vsd_delta must be > 0 mm, got {delta}")
    except Exception as e:  # noqa: BLE001
        message = _data_error(e)
        if message is None:
            raise
        print(f"posediff score: {message}", file=sys.stderr)
        return 2
    images = {i.key[:2] for i in datamodule.targets}
    print(
        f"BOP data {datamodule.root}, {datamodule.test_split}: {len(datamodule.targets)} targets in "
        f"{len(images)} images; {len(rows)} estimates in {csv}"
    )
    result = score_estimates(datamodule, rows, vsd=bool(cfg.vsd), vsd_delta=float(delta))
    result.update(
        csv=str(csv),
        seconds=time.perf_counter() - start,
        vsd_delta=float(delta),
        data={k: OmegaConf.to_container(cfg.data, resolve=True).get(k) for k in
              ("root", "test_split", "targets", "models_dir", "eval_models_dir", "obj_ids")},
    )  # fmt: skip
    atomic_write_json(out_dir / "metrics.json", result)
    table = run_table(result)
    atomic_write_text(out_dir / "metrics.md", table)
    print(table)
    print(f"{headline(result)}; metrics: {out_dir / 'metrics.json'}")
    return 0


def distill(cfg: DictConfig) -> int:
    """``posediff distill ckpt_path=TEACHER steps=5``: a few-step student (:mod:`posediff.training.distill`) trained
    on the teacher's own training data, written as a normal checkpoint (``out``, default
    ``<run>/checkpoints/last.ckpt``) plus ``distill.json`` in the run folder."""
    import lightning as L

    from ._io import atomic_write_json
    from .models import (
        CONFIG_KEY,
        CheckpointError,
        PoseDiffusionModule,
        module_from_checkpoint,
        read_checkpoint,
    )
    from .training.distill import DistillationError, SegmentDistillation, save_student

    command = "posediff distill"
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
        ckpt = read_checkpoint(cfg.ckpt_path)
        teacher = module_from_checkpoint(ckpt, cfg.ckpt_path)
        if not isinstance(teacher, PoseDiffusionModule) or not hasattr(teacher.sampler, "step"):
            raise DistillationError(
                f"checkpoint {cfg.ckpt_path} is a {type(teacher).__name__}, not a diffusion model: "
                "posediff distill needs a score model trained by posediff fit"
            )
        levels = teacher.diffusion.schedule.num_levels
        steps = _whole(cfg.steps, "steps", 1, levels)
        _whole(cfg.substeps, "substeps")
        _whole(cfg.num_hypotheses, "num_hypotheses")
        _whole(cfg.reuse, "reuse")
        _whole(cfg.max_steps, "max_steps")
        if not (float(cfg.lr) > 0 and float(cfg.lr_final) > 0):
            raise DistillationError(f"lr and lr_final must be > 0, got {cfg.lr} and {cfg.lr_final}")
        run = OmegaConf.create(ckpt[CONFIG_KEY])
        if cfg.get("data"):
            run.data = OmegaConf.merge(run.data, OmegaConf.to_container(cfg.data, resolve=False))
        out = Path(str(cfg.out)) if cfg.out else out_dir / "checkpoints" / "last.ckpt"
        if out.is_dir():
            raise DistillationError(f"out={out} is a folder; give the student checkpoint's file name")
        datamodule = instantiate(run.data)
        datamodule.setup("fit")
    except (CheckpointError, DistillationError, ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"{command}: {_data_error(e) or e}", file=sys.stderr)
        return 2
    print(datamodule.describe())
    distiller = SegmentDistillation(
        teacher,
        steps=steps,
        substeps=int(cfg.substeps),
        num_hypotheses=int(cfg.num_hypotheses),
        reuse=int(cfg.reuse),
        lr=float(cfg.lr),
        lr_final=float(cfg.lr_final),
    )
    print(
        f"student: {steps} few_step steps (σ {', '.join(f'{s:.3g}' for s in distiller.sig_t)} → 0); "
        f"teacher: {cfg.substeps} Heun steps per student step"
    )
    _lightning_logs_to_stdout()
    callbacks = list(instantiate(cfg.trainer.get("callbacks")) or [])
    if not cfg.trainer.get("enable_progress_bar", True):
        from lightning.pytorch.callbacks import ProgressBar

        callbacks = [c for c in callbacks if not isinstance(c, ProgressBar)]
    trainer = instantiate(cfg.trainer, callbacks=callbacks)
    start = time.perf_counter()
    trainer.fit(distiller, datamodule=datamodule)
    seconds = time.perf_counter() - start
    losses = distiller.loss_history
    record = {
        "teacher": str(cfg.ckpt_path),
        "method": "segment",
        "steps": steps,
        "substeps": int(cfg.substeps),
        "num_hypotheses": int(cfg.num_hypotheses),
        "reuse": int(cfg.reuse),
        "updates": int(trainer.global_step),
        "lr": float(cfg.lr),
        "lr_final": float(cfg.lr_final),
        "seconds": seconds,
        "loss_first": _mean(losses[:50]),
        "loss_last": _mean(losses[-50:]),
    }
    student = distiller.student.cpu().eval()
    config = distiller.student_config(OmegaConf.to_container(run, resolve=True), record)
    path = save_student(student, config, out)
    atomic_write_json(out_dir / "distill.json", {**record, "student": str(path)})
    print(
        f"distilled {record['updates']} updates in {seconds:.0f} s; loss {record['loss_first']:.4f} → "
        f"{record['loss_last']:.4f}"
    )
    print(f"student: {path} (sampler few_step, num_steps={steps})")
    print(f"next:    posediff eval ckpt_path={path}")
    return 0


def export_checkpoint(cfg: DictConfig) -> int:
    """``posediff export``: a checkpoint's graphs in ONNX / TorchScript / ExportedProgram
    (:func:`posediff.models.export.export_module`), written to ``<out>.partial`` and renamed.

    The step count the sampler graph unrolls is settled (:func:`posediff.models.export.unrolled_steps`:
    ``num_steps``, else the checkpoint's sampler's, else the default; above ``max_unrolled`` refused)
    and printed before the export starts. A write that fails (a full disk) is one line naming the
    folder, and the unfinished ``.partial`` folder is removed: nothing is left in ``out``."""
    from ._io import OutputFolderError, check_output_dir, make_output_dir, remove_own_dir, replace_dir
    from .models import CheckpointError, PoseDiffusionModule, load_checkpoint
    from .models.export import FORMATS, ExportError, ExportWriteError, export_module, unrolled_steps

    command = "posediff export"
    try:
        fmt = str(cfg.format)
        if fmt not in FORMATS:
            raise ExportError(f"unknown format {fmt!r}; choose one of: {', '.join(FORMATS)}")
        _whole(cfg.num_samples, "num_samples", 2)
        if cfg.num_steps is not None:
            _whole(cfg.num_steps, "num_steps")
        max_unrolled = cfg.get("max_unrolled")
        if max_unrolled is not None:
            _whole(max_unrolled, "max_unrolled")
        out = Path(str(cfg.out)) if cfg.out else Path(HydraConfig.get().runtime.output_dir) / fmt
        if out.exists() and not cfg.overwrite:
            raise ExportError(f"out={out} already exists; give a new folder or overwrite=true")
        check_output_dir(out, command, replace=True, key="out")  # only a folder posediff made is replaced
        module = load_checkpoint(cfg.ckpt_path)
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
            run = OmegaConf.create(config)
            example = next(iter(_data(run).test_dataloader()))[module.cond_key][:1]
        num_steps = None if cfg.num_steps is None else int(cfg.num_steps)
        steps, source = unrolled_steps(module.sampler, fmt, num_steps, max_unrolled)
    except (CheckpointError, ExportError, OutputFolderError, ValueError, FileNotFoundError) as e:
        print(f"{command}: {_data_error(e) or e}", file=sys.stderr)
        return 2
    why = {"num_steps": f"num_steps={steps}", "sampler": "the checkpoint's sampler's own count",
           "default": "the default; the checkpoint's sampler sets none"}[source]  # fmt: skip
    print(f"{command}: unrolling {steps} sampling step{'s' * (steps != 1)} into the {fmt} sampler graph "
          f"({why}); num_steps=N changes it", flush=True)  # fmt: skip
    partial = out.with_name(out.name + ".partial")
    remove_own_dir(partial, command)  # refuses (one line) a .partial folder posediff did not make
    try:
        make_output_dir(partial, command)
        files = export_module(
            module, partial, fmt, example=example, num_steps=steps, num_samples=int(cfg.num_samples),
            info={"ckpt_path": str(cfg.ckpt_path), "image_size": size or None}, max_unrolled=max_unrolled,
        )  # fmt: skip
        replace_dir(partial, out, command)
    except (ExportError, OutputFolderError) as e:
        remove_own_dir(partial, command)
        print(f"{command}: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # ExportWriteError (a graph or the JSON), or the folder / marker (a full disk)
        remove_own_dir(partial, command)
        msg = str(e) if isinstance(e, ExportWriteError) else (
            f"cannot write in {partial}: {e.strerror or e}; free space there or choose another out="
        )  # fmt: skip
        print(f"{command}: out={out}: {msg}", file=sys.stderr)
        return 2
    except BaseException:
        remove_own_dir(partial, command)
        raise
    for name, path in files.items():
        print(f"{name}: {out / path.name}")
    return 0


def report(cfg: DictConfig) -> int:
    """``posediff report dir=<multirun folder>``: the jobs' metrics in one table (Table 4 layout)."""
    from .evaluation.report import collect_sweep

    try:
        _, table = collect_sweep(str(cfg.dir))
    except FileNotFoundError as e:
        print(f"posediff report: {e}", file=sys.stderr)
        return 2
    print(table)
    print(f"report: {Path(str(cfg.dir)) / 'report.md'}")
    return 0


def predict(cfg: DictConfig) -> int:
    """``posediff predict``: hypotheses, modes, ``poses.npz`` / ``poses.json`` and the plots for one
    image file (``image=``) or one test sample (``index=``; what it needs comes from the data module,
    :meth:`posediff.data.PoseDataModule.prediction_input`)."""
    from .config.allowlist import target_class
    from .evaluation import decode_prediction, image_tensor, predict, read_image, save_prediction
    from .models import CheckpointError

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        if (cfg.image is None) == (cfg.index is None):
            raise ValueError("give exactly one of image=PATH (an image file) or index=N (a test sample)")
        _whole(cfg.num_samples, "num_samples")
        if cfg.index is not None:
            _whole(cfg.index, "index", 0)
        _whole(cfg.top_modes, "top_modes", 0)
        if not float(cfg.mode_radius_deg) > 0:
            raise ValueError(f"mode_radius_deg must be > 0, got {cfg.mode_radius_deg}")
        device = _device(str(cfg.device))
        picture = read_image(str(cfg.image)) if cfg.image is not None else None  # checked before the model
        module, run = _checkpoint_run(cfg)
        data_cls = target_class(OmegaConf.to_container(run.data), where="checkpoint data")  # allow-listed
        if getattr(data_cls, "needs_test_target", False) and cfg.index is None:
            raise ValueError(
                f"checkpoint {cfg.ckpt_path} was trained on {data_cls.__name__} data: a prediction needs a test "
                "target's box, mask and camera — give index=N (a target of its test split), not image="
            )
        size = int(run.data.get("image_size", 0) or 0)
        if module.cond_key != "image" or not size:
            raise ValueError(
                f"checkpoint {cfg.ckpt_path} was not trained on images (condition {module.cond_key!r})"
            )
        if cfg.index is not None:
            inp = _data(run).prediction_input(int(cfg.index))
        else:
            K, offset = data_cls.image_camera(run.data)
            inp = {"image": image_tensor(picture, size), "K": K, "camera_offset": offset, "gt_pose": None}
            if cfg.shape is not None:
                from .symmetry import shape_name

                inp["shape"] = shape_name(cfg.shape)
    except (CheckpointError, ValueError, FileNotFoundError, IndexError, KeyError) as e:
        print(f"posediff predict: {_data_error(e) or e}", file=sys.stderr)
        return 2
    module.to(device)
    pred = predict(
        module,
        inp["image"],
        num_samples=int(cfg.num_samples),
        trajectory=bool(cfg.trajectory),
        seed=int(cfg.seed),
        mode_radius_deg=float(cfg.mode_radius_deg),
        min_mode_weight=float(cfg.min_mode_weight),
    )
    if inp.get("decode") is not None:  # network poses → camera frame (BOP: mm)
        pred = decode_prediction(
            pred,
            inp["decode"],
            module.group,
            mode_radius_deg=float(cfg.mode_radius_deg),
            mode_translation_radius=float(inp.get("mode_translation_radius", 20.0)),
            min_mode_weight=float(cfg.min_mode_weight),
        )
    files = save_prediction(
        pred,
        out_dir,
        image=inp["image"],
        K=inp.get("K"),
        camera_offset=inp.get("camera_offset"),
        shape=inp.get("shape"),
        mesh=inp.get("mesh"),
        gt_pose=inp.get("gt_pose"),
        gt_rotations=inp.get("gt_rotations"),
        top_modes=int(cfg.top_modes),
        info={
            "ckpt_path": str(cfg.ckpt_path),
            "image": None if cfg.image is None else str(cfg.image),
            "index": cfg.index,
            "shape": inp.get("shape"),
            **inp.get("info", {}),
            "group": module.group.name,
            "sampler": OmegaConf.to_container(run.module.sampler, resolve=True),
        },
    )
    title = f"{inp['title']}: " if inp.get("title") else ""
    print(f"{title}{pred.modes.summary()} from {pred.samples.shape[0]} hypotheses in {pred.seconds:.2f} s")
    for k in range(min(len(pred.modes), int(cfg.top_modes))):
        line = f"  mode {k}: weight {float(pred.modes.weights[k]):.3f}"
        if inp.get("decode") is not None:
            t = pred.modes.poses[k, :3, 3].tolist()
            line += f", t = ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm"
        print(line)
    for name, path in files.items():
        print(f"{name}: {path}")
    return 0
