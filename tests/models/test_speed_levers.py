"""The training-speed levers compute the same thing (benchmarks/train_step.py measures their speed).

* ``module.optimizer_impl=foreach|fused``: Adam's multi-tensor and fused updates give the weights the
  default for-loop update gives, step for step;
* ``module.channels_last``: the encoder's outputs and gradients are those of the contiguous layout;
* ``module.compile``: refused with a warning where inductor cannot run (no C++ compiler), and (slow)
  the compiled networks' loss and gradients equal the eager ones;
* the anchor's symmetric rotation loss is computed once per step, with the value it had.
"""

from __future__ import annotations

import copy
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from torch.testing import assert_close

from posediff import hardware
from posediff.config import register_resolvers
from posediff.models import base as module_base

ROOT = Path(__file__).resolve().parents[2]
TOY = ["+experiment=toy_so3", "data.num_train=64", "data.batch_size=8", "module.num_noisy=4",
       "denoiser.hidden_dim=16"]  # fmt: skip


def _compose(overrides: list[str]):  # noqa: ANN202 - DictConfig
    register_resolvers()
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("fit", overrides=overrides)


def _fit(overrides: list[str], steps: int) -> dict[str, torch.Tensor]:
    cfg = _compose(overrides)
    L.seed_everything(0, workers=True, verbose=False)
    datamodule = instantiate(cfg.data)
    module = instantiate(cfg.module)
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0)  # fmt: skip
    trainer.fit(module, datamodule=datamodule)
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


@pytest.mark.parametrize("impl", ["foreach", "fused"])
def test_adam_implementations_give_the_same_weights(impl: str) -> None:
    """Six steps of the toy: every weight as with the default update (float32 rounding apart)."""
    base = _fit(TOY, 6)
    other = _fit([*TOY, f"module.optimizer_impl={impl}"], 6)
    assert base.keys() == other.keys()
    start = _initial(TOY)
    assert any(not torch.equal(base[k], start[k]) for k in base if base[k].is_floating_point()), (
        "weights moved"
    )
    for k in base:
        assert_close(other[k], base[k], atol=2e-6, rtol=1e-5, msg=k)


def _initial(overrides: list[str]) -> dict[str, torch.Tensor]:
    cfg = _compose(overrides)
    L.seed_everything(0, workers=True, verbose=False)
    instantiate(cfg.data)
    return {k: v.detach().clone() for k, v in instantiate(cfg.module).state_dict().items()}


def test_an_unknown_optimizer_impl_is_one_line() -> None:
    cfg = _compose([*TOY, "module.optimizer_impl=sgd"])
    with pytest.raises(
        Exception, match="unknown optimizer_impl 'sgd'; choose one of: default, foreach, fused"
    ):
        instantiate(cfg.module)


@pytest.mark.parametrize("key", ["channels_last", "compile"])
def test_a_lever_that_is_not_a_bool_is_one_line(key: str) -> None:
    cfg = _compose([*TOY, f"module.{key}=abc"])
    with pytest.raises(Exception, match=f"module.{key} must be true or false, got 'abc'"):
        instantiate(cfg.module)


def test_channels_last_encoder_computes_the_same() -> None:
    """The locate-then-crop ResNet in channels-last order: the same encoding and the same gradients."""
    from posediff.nn import PoseEncoder

    torch.manual_seed(0)
    enc = PoseEncoder(image_size=64, crop_size=32, out_dim=16, crop_jitter=0.0).train()
    other = copy.deepcopy(enc).to(memory_format=torch.channels_last)
    conv = next(m for m in other.modules() if isinstance(m, torch.nn.Conv2d))
    assert conv.weight.is_contiguous(memory_format=torch.channels_last)
    image = torch.rand(4, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    pose = torch.eye(4).repeat(4, 1, 1)
    outs = []
    for e in (enc, other):
        out = e(image, pose=pose)
        loss = out.feature.square().sum() + out.located.square().sum()
        loss.backward()
        outs.append(
            (out.feature.detach(), {n: p.grad.clone() for n, p in e.named_parameters() if p.grad is not None})
        )
    assert_close(outs[1][0], outs[0][0], atol=1e-4, rtol=1e-4)
    assert outs[0][1].keys() == outs[1][1].keys()
    # per tensor, relative to its norm (measured ≤ 1.3e-4), or below 1e-6 where a gradient is itself
    # round-off (the locator's biases before a softmax: ~1e-7 in either layout)
    for n, g in outs[0][1].items():
        d = float((outs[1][1][n] - g).norm())
        assert d <= 1e-3 * float(g.norm()) + 1e-6, (n, d, float(g.norm()))


def test_compile_without_a_compiler_warns_and_stays_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert "C++ compiler" in (hardware.compile_problem() or "")
    cfg = _compose([*TOY, "module.compile=true"])
    m = instantiate(cfg.module)
    with pytest.warns(UserWarning, match="module.compile=true ignored"):
        m.on_fit_start()
    assert m.denoiser._compiled_call_impl is None


def _side_loss_batch(m, n: int = 4) -> tuple[dict, object]:  # noqa: ANN001
    from posediff.lie import SO3
    from posediff.nn.pose_encoder import Encoding

    g = torch.Generator().manual_seed(2)
    R = SO3().sample_uniform((n,), generator=g)
    pose = torch.eye(4).repeat(n, 1, 1)
    pose[:, :3, :3] = R
    batch = {"pose": pose, "shape": torch.tensor([0, 1, 2, 3][:n])}
    Rhat = SO3().sample_uniform((n,), generator=g).requires_grad_(True)
    enc = Encoding(torch.zeros(n, 4), Rhat, None, None, None, None, None, None)
    return batch, enc


def test_the_symmetric_rotation_loss_is_computed_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 6-D anchor with the auxiliary loss: one call of ``symmetric_rotation_loss`` per step (there were
    two: one for the logged error, one for the loss), and the same loss and gradient as two calls."""
    cfg = _compose([*TOY, "module.aux_weight=1.0"])
    m = instantiate(cfg.module)
    m.log = lambda *a, **k: None
    calls = []
    real = module_base.symmetric_rotation_loss

    def counted(batch, R):  # noqa: ANN001, ANN202
        calls.append(R.requires_grad)
        return real(batch, R)

    monkeypatch.setattr(module_base, "symmetric_rotation_loss", counted)
    batch, enc = _side_loss_batch(m)
    total = m.side_losses(batch, enc, "train")
    assert calls == [True], calls
    (grad,) = torch.autograd.grad(total, enc.rotation)
    expected = real(batch, enc.rotation).mean()
    (grad_expected,) = torch.autograd.grad(expected, enc.rotation)
    assert_close(total, expected)
    assert_close(grad, grad_expected)


@pytest.mark.slow
def test_compiled_networks_give_the_eager_loss_and_gradients() -> None:
    """``module.compile=true`` (inductor on the CPU): the first steps' weights as eager ones."""
    from posediff.hardware import compile_problem

    if compile_problem() is not None:
        pytest.skip(compile_problem())
    base = _fit(TOY, 3)
    compiled = _fit([*TOY, "module.compile=true"], 3)
    for k in base:
        assert_close(compiled[k], base[k], atol=1e-5, rtol=1e-4, msg=k)


@pytest.mark.slow
def test_quickstart_learns_the_same_with_the_defaults() -> None:
    """500 steps of ``quickstart`` (benchmarks/train_step.py's small render), seeds 0 and 1, on the code path
    before the levers and with posediff's defaults: the held-out loss moves by no more than the seeds move it
    (``python benchmarks/train_step.py --curve 500`` records the same in train_step_curve.json)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_step", ROOT / "benchmarks" / "train_step.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.ensure_data()
    val = {
        (path, seed): bench.fit_curve([*bench.EXPERIMENTS["quickstart"], *extra, f"seed={seed}"], 500)[
            "val_loss"
        ]
        for path, extra in (("today", bench.TODAY), ("defaults", []))
        for seed in (0, 1)
    }
    seed_gap = abs(val["today", 0] - val["today", 1])
    path_gap = max(abs(val["today", s] - val["defaults", s]) for s in (0, 1))
    assert path_gap <= seed_gap, val


@pytest.mark.parametrize("seed", [0, 1])
def test_bf16_autocast_encoder_follows_float32(seed: int) -> None:
    """``trainer.precision=bf16-mixed`` (what ``${posediff.fast_precision:}`` picks where the CPU has native
    bf16; emulated elsewhere, so this runs everywhere): the locate-then-crop ResNet's encoding and its
    gradients under CPU bf16 autocast point where float32's do — bf16 keeps 8 bits of mantissa, so the
    check is relative. At quickstart's sizes (128 px, 64 px crops, batch 16; smaller crops leave the last
    BatchNorm a few values per channel, which amplifies any rounding) measured on seeds 0–2: feature error
    3.4–4.1 % of its norm, gradient cosine 0.934–0.946; whether it learns alike is
    ``benchmarks/train_step.py --curve 500 --curve-paths defaults defaults_bf16``."""
    from posediff.nn import PoseEncoder

    torch.manual_seed(seed)
    enc = PoseEncoder(image_size=128, crop_size=64, out_dim=64, crop_jitter=0.0).train()
    image = torch.rand(16, 3, 128, 128, generator=torch.Generator().manual_seed(seed + 10))
    pose = torch.eye(4).repeat(16, 1, 1)
    outs = []
    for bf16 in (False, True):
        enc.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = enc(image, pose=pose)
        loss = out.feature.float().square().sum() + out.located.float().square().sum()
        loss.backward()
        grads = torch.cat([p.grad.flatten() for p in enc.parameters() if p.grad is not None])
        outs.append((out.feature.detach().float(), grads))
    (f32, g32), (fbf, gbf) = outs
    assert fbf.dtype == torch.float32 and bool(torch.isfinite(gbf).all())
    assert float((fbf - f32).norm()) <= 0.1 * float(f32.norm())
    cos = float(torch.nn.functional.cosine_similarity(g32, gbf, dim=0))
    assert cos >= 0.85, cos
