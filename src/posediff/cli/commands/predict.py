"""``posediff predict ckpt_path=CKPT image=IMG.png | index=N``: hypotheses, modes, ``poses.npz`` /
``poses.json`` and the plots for one image file or one test sample (what it needs comes from the
data module, :meth:`posediff.data.PoseDataModule.prediction_input`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ...config.allowlist import target_class
from ...evaluation import decode_prediction, image_tensor, predict, read_image, save_prediction
from ...options import whole
from ...symmetry import shape_name
from ..errors import user_input
from ..runs import checkpoint_run, device, test_data


def run(cfg: DictConfig) -> int:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    with user_input(ValueError, FileNotFoundError, IndexError, KeyError):
        module, run_cfg, inp, dev = prediction_input(cfg)
    module.to(dev)
    pred = predict(module, inp["image"], num_samples=int(cfg.num_samples), trajectory=bool(cfg.trajectory),
                   seed=int(cfg.seed), mode_radius_deg=float(cfg.mode_radius_deg),
                   min_mode_weight=float(cfg.min_mode_weight))  # fmt: skip
    if inp.get("decode") is not None:  # network poses → camera frame (BOP: mm)
        pred = decode_prediction(pred, inp["decode"], module.group, mode_radius_deg=float(cfg.mode_radius_deg),
                                 mode_translation_radius=float(inp.get("mode_translation_radius", 20.0)),
                                 min_mode_weight=float(cfg.min_mode_weight))  # fmt: skip
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
            "sampler": OmegaConf.to_container(run_cfg.module.sampler, resolve=True),
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


def prediction_input(cfg: DictConfig) -> tuple[Any, DictConfig, dict[str, Any], Any]:
    """The options checked, then the model, its run config, the input (image, camera, what to draw)
    and the device; the image file is read before the model."""
    if (cfg.image is None) == (cfg.index is None):
        raise ValueError("give exactly one of image=PATH (an image file) or index=N (a test sample)")
    whole(cfg.num_samples, "num_samples")
    if cfg.index is not None:
        whole(cfg.index, "index", 0)
    whole(cfg.top_modes, "top_modes", 0)
    if not float(cfg.mode_radius_deg) > 0:
        raise ValueError(f"mode_radius_deg must be > 0, got {cfg.mode_radius_deg}")
    dev = device(str(cfg.device))
    picture = read_image(str(cfg.image)) if cfg.image is not None else None  # checked before the model
    module, run_cfg = checkpoint_run(cfg, "posediff predict")
    data_cls = target_class(OmegaConf.to_container(run_cfg.data), where="checkpoint data")  # allow-listed
    if getattr(data_cls, "needs_test_target", False) and cfg.index is None:
        raise ValueError(
            f"checkpoint {cfg.ckpt_path} was trained on {data_cls.__name__} data: a prediction needs a test "
            "target's box, mask and camera — give index=N (a target of its test split), not image="
        )
    size = int(run_cfg.data.get("image_size", 0) or 0)
    if module.cond_key != "image" or not size:
        raise ValueError(
            f"checkpoint {cfg.ckpt_path} was not trained on images (condition {module.cond_key!r})"
        )
    if cfg.index is not None:
        inp = test_data(run_cfg).prediction_input(int(cfg.index))
    else:
        K, offset = data_cls.image_camera(run_cfg.data)
        inp = {"image": image_tensor(picture, size), "K": K, "camera_offset": offset, "gt_pose": None}
        if cfg.shape is not None:
            inp["shape"] = shape_name(cfg.shape)
    return module, run_cfg, inp, dev
