"""The contract every image pose model meets — the paper's diffusion model, the anchored denoiser (with or
without the auxiliary loss, with or without locate-then-crop) and the regression baselines — so that
training, evaluation, ``predict`` and the samplers treat them alike.

``pose_model_contract(module, batch)`` runs every check on a module and a batch in the data's layout
(``image``, ``pose``, ``rotation``, ``translation``, ``shape``); :func:`synthetic_batch` makes one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from ..models import PoseDiffusionModule


def synthetic_batch(
    batch_size: int = 4, image_size: int = 32, group: str = "se3", seed: int = 0
) -> dict[str, Tensor]:
    """Random images and SYMSOL-T-like poses (translation in [−1, 1]³ from the scene centre)."""
    from ..lie import SO3

    g = torch.Generator().manual_seed(seed)
    R = SO3().sample_uniform((batch_size,), generator=g)
    t = torch.rand(batch_size, 3, generator=g) * 2 - 1
    pose = R if group == "so3" else torch.eye(4).repeat(batch_size, 1, 1)
    if group != "so3":
        pose[:, :3, :3], pose[:, :3, 3] = R, t
    return {
        "image": torch.rand(batch_size, 3, image_size, image_size, generator=g),
        "pose": pose,
        "rotation": R,
        "translation": t,
        "shape": torch.arange(batch_size) % 5,
    }


def check_training_step(module: Any, batch: dict[str, Tensor]) -> None:
    """A training step gives a finite loss whose gradients are finite and reach the encoder."""
    module.train()
    module.zero_grad()
    loss = module.training_step(batch, 0)
    assert loss.ndim == 0 and torch.isfinite(loss), f"training loss {loss}"
    loss.backward()
    grads = [p.grad for p in module.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads), "non-finite gradients"
    enc = [p.grad for p in module.encoder.parameters() if p.grad is not None]
    assert enc and sum(float(g.abs().sum()) for g in enc) > 0, "no gradient reaches the encoder"
    module.zero_grad()


def check_validation_step(module: Any, batch: dict[str, Tensor]) -> None:
    module.eval()
    loss = module.validation_step(batch, 0)
    assert torch.isfinite(loss), f"validation loss {loss}"


def check_samples(module: Any, batch: dict[str, Tensor]) -> None:
    """``sample`` gives ``(B, N, n, n)`` group elements (and a trajectory), deterministic per seed."""
    module.eval()
    g, n = module.group, int(module.group.matrix_dim)
    B = int(batch["pose"].shape[0])
    x = module.sample(batch[module.cond_key], 5, 3, generator=torch.Generator().manual_seed(0))
    assert x.shape == (B, 5, n, n), f"samples of shape {tuple(x.shape)}"
    assert torch.isfinite(x).all()
    g.check(x)
    y = module.sample(batch[module.cond_key], 5, 3, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(x, y)
    x2, path = module.sample(
        batch[module.cond_key], 2, 3, generator=torch.Generator().manual_seed(1), trajectory=True
    )
    assert x2.shape == (B, 2, n, n) and path.shape[1:] == (B, 2, n, n)
    torch.testing.assert_close(path[-1], x2)


def check_condition_is_one_tensor(module: Any, batch: dict[str, Tensor]) -> None:
    """The condition the samplers carry is one ``(B, C)`` tensor that the denoiser accepts."""
    if not isinstance(module, PoseDiffusionModule):  # a regression model carries no condition to a sampler
        return
    module.eval()
    with torch.no_grad():
        cond = module.encode(batch[module.cond_key])
        assert isinstance(cond, Tensor) and cond.shape[0] == batch["pose"].shape[0]
        x = batch["pose"].unsqueeze(1).expand(-1, 3, -1, -1)
        sigma = torch.full(x.shape[:2], 0.1)
        out = module(x, sigma, cond)
    assert out.shape == (*x.shape[:2], module.group.dim) and torch.isfinite(out).all()


POSE_MODEL_CHECKS: dict[str, Callable[[Any, dict[str, Tensor]], None]] = {
    "training_step": check_training_step,
    "validation_step": check_validation_step,
    "samples": check_samples,
    "condition_is_one_tensor": check_condition_is_one_tensor,
}


def pose_model_contract(module: Any, batch: dict[str, Tensor]) -> None:
    """Run every check of :data:`POSE_MODEL_CHECKS` on ``module`` with ``batch``."""
    for check in POSE_MODEL_CHECKS.values():
        check(module, batch)


__all__ = ["POSE_MODEL_CHECKS", "pose_model_contract", "synthetic_batch"]
