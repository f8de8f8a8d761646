"""``posediff export``: the exported encoder, denoiser and sampling loop give the eager model's poses
on the same inputs, for every group (so3, r3so3, se3) and format; the loop with posediff's own draws
is ``module.sample``."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from posediff.cli import config_dir
from posediff.config import register_resolvers
from posediff.models.export import SamplingLoop, draw_inputs, export_module, load_exported, noise_steps

GROUPS = {"so3": "toy_so3", "r3so3": "toy_se3", "se3": "toy_se3"}
STEPS, N = 3, 5


def _model(group: str):  # noqa: ANN202 - (module, example condition)
    register_resolvers()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("fit", overrides=[f"+experiment={GROUPS[group]}", f"group={group}", "denoiser.hidden_dim=16",
                                        "sampler=few_step", "sampler.renoise=0.5"])  # fmt: skip
    torch.manual_seed(0)
    module = instantiate(cfg.module).eval()
    dm = instantiate(cfg.data)
    dm.setup("test")
    return module, next(iter(dm.test_dataloader()))[module.cond_key][:2]


@pytest.fixture(scope="module", params=list(GROUPS))
def model(request: pytest.FixtureRequest):  # noqa: ANN201
    return request.param, *_model(request.param)


def _check(module, example, folder: Path, steps: int) -> float:  # noqa: ANN001
    # ONNX loads as is; TorchScript and torch.export files load with trust=True (files we made ourselves)
    meta, run = load_exported(folder, trust=folder.name != "onnx")
    assert meta["group"] == module.group.name and meta["num_steps"] == steps
    assert len(meta["sigma_t"]) == steps and meta["noise_steps"] == noise_steps(module.sampler, steps)
    g = torch.Generator().manual_seed(3)
    x0, noise = draw_inputs(module.sampler, steps, example.shape[0], N, generator=g)
    with torch.no_grad():
        cond = module.encode(example)
        ref = SamplingLoop(module, module.sampler, steps)(cond, x0, noise)
        sigma = torch.full((example.shape[0], N), meta["sigma_t"][0])
        torch.testing.assert_close(run["encoder"](example), cond, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(
            run["denoiser"](x0, sigma, cond), module(x0, sigma, cond), atol=1e-4, rtol=1e-4
        )
        got = run["sampler"](run["encoder"](example), x0, noise)
    torch.testing.assert_close(got, ref, atol=1e-4, rtol=1e-4)
    return float((got - ref).abs().max())


def test_the_loop_with_posediffs_draws_is_module_sample(model) -> None:  # noqa: ANN001
    _, module, example = model
    assert any(noise_steps(module.sampler, STEPS))  # renoise: the loop reads noise
    x0, noise = draw_inputs(
        module.sampler, STEPS, example.shape[0], N, generator=torch.Generator().manual_seed(7)
    )
    with torch.no_grad():
        loop = SamplingLoop(module, module.sampler, STEPS)(module.encode(example), x0, noise)
        eager = module.sample(example, N, STEPS, generator=torch.Generator().manual_seed(7))
    assert torch.equal(loop, eager)


def test_torchscript_on_every_group(model, tmp_path: Path) -> None:  # noqa: ANN001
    _, module, example = model
    export_module(module, tmp_path / "ts", "torchscript", example=example, num_steps=STEPS, num_samples=N)
    assert _check(module, example, tmp_path / "ts", STEPS) == 0.0


@pytest.mark.parametrize("fmt", ["onnx", pytest.param("exported_program", marks=pytest.mark.slow)])
def test_exported_program_and_onnx(fmt: str, tmp_path: Path) -> None:  # ONNX goes through torch.export
    module, example = _model("se3")
    export_module(module, tmp_path / fmt, fmt, example=example[:1], num_steps=1, num_samples=N)
    _check(module, torch.cat([example, example[:1]]), tmp_path / fmt, 1)  # 3 inputs, not the example's 1 (2)
    meta, _ = load_exported(tmp_path / fmt, trust=fmt != "onnx")
    assert all(meta["dynamic"].values()), meta["dynamic"]


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["exported_program", "onnx"])
def test_every_format_on_every_group(model, fmt: str, tmp_path: Path) -> None:  # noqa: ANN001
    _, module, example = model
    export_module(module, tmp_path / fmt, fmt, example=example, num_steps=STEPS, num_samples=N)
    _check(module, example, tmp_path / fmt, STEPS)


def test_bad_options(tmp_path: Path) -> None:
    from posediff.models.export import ExportError

    module, example = _model("so3")
    with pytest.raises(ExportError, match="unknown format 'tflite'"):
        export_module(module, tmp_path, "tflite", example=example)
    with pytest.raises(ExportError, match=r"num_steps must be in \[1, "):
        export_module(module, tmp_path, "torchscript", example=example, num_steps=0)
