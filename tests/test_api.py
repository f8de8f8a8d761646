"""The top-level API and Lightning's own entry point: a checkpoint loads as a user of such a package
expects, and only through the allow-list."""

import copy
from pathlib import Path

import pytest
import torch

import posediff
from posediff.cli import main
from posediff.models import CONFIG_KEY, CheckpointError, PoseDiffusionModule

TOY = ["+experiment=toy_so3", "trainer.max_steps=2", "trainer.val_check_interval=2",
       "trainer.enable_progress_bar=false", "data.num_train=64", "data.batch_size=8",
       "data.num_test_per_shape=1", "module.num_noisy=4", "denoiser.hidden_dim=16", "eval.before=false",
       "eval.num_samples=2", "eval.num_steps=[2]", "eval.samplers=null"]  # fmt: skip


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "run"
    assert main(["fit", *TOY, f"hydra.run.dir={out}"]) == 0
    return out / "checkpoints" / "last.ckpt"


def test_the_public_api_is_at_the_top_level() -> None:
    for name in (
        "load_checkpoint",
        "predict",
        "PoseRegressionModule",
        "Prediction",
        "PoseDiffusionModule",
        "SymmetrySet",
        "modes",
        "SE3",
    ):
        assert name in posediff.__all__ and getattr(posediff, name) is not None
    from importlib.metadata import version

    assert posediff.__version__ == version("posediff")
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        posediff.nope  # noqa: B018


def test_load_from_checkpoint_is_load_checkpoint(ckpt: Path) -> None:
    a = PoseDiffusionModule.load_from_checkpoint(ckpt)
    b = posediff.load_checkpoint(ckpt)
    assert type(a) is type(b) and not a.training
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert ka == kb and torch.equal(va, vb)
    assert a.config == b.config and a.hparams[CONFIG_KEY] == a.config  # save_hyperparameters
    raw = torch.load(ckpt, weights_only=True, map_location="cpu")
    assert raw["hyper_parameters"][CONFIG_KEY] == raw["posediff_config"]
    with pytest.raises(TypeError, match="not supported"):
        PoseDiffusionModule.load_from_checkpoint(ckpt, lr=1.0)


def test_load_from_checkpoint_refuses_a_tampered_config(ckpt: Path, tmp_path: Path) -> None:
    sentinel = tmp_path / "precious.txt"
    sentinel.write_text("keep")
    raw = torch.load(ckpt, weights_only=True, map_location="cpu")
    bad = copy.deepcopy(raw)
    payload = {"_target_": "builtins.open", "_args_": [str(sentinel), "w"]}
    bad["posediff_config"]["module"]["lr"] = payload
    bad["hyper_parameters"][CONFIG_KEY]["module"]["lr"] = payload
    path = tmp_path / "bad.ckpt"
    torch.save(bad, path)
    with pytest.raises(CheckpointError, match="builtins.open"):
        PoseDiffusionModule.load_from_checkpoint(path)
    assert sentinel.read_text() == "keep"


def test_the_evaluation_names_live_in_posediff_evaluation() -> None:
    """One home per name: the evaluation API is ``posediff.evaluation`` (and its submodules); the four
    top-level shims (``posediff.evaluate``, ``evaluate_bop``, ``report``, ``predict`` as a module) are gone
    (CHANGELOG), and ``posediff.predict`` is the function."""
    import importlib

    names = {
        "posediff.evaluation.shapes": ("evaluate", "ROTATION_THRESHOLDS_DEG", "TRANSLATION_THRESHOLDS"),
        "posediff.evaluation.sampling": ("SampledBatches",),
        "posediff.evaluation.bop": ("evaluate_bop", "predict_targets", "score_estimates", "check_estimates"),
        "posediff.evaluation.report": ("run_table", "axis_table", "sweep_rows", "sweep_table", "collect_sweep",
                                       "ReportCallback"),
        "posediff.evaluation.predict": ("predict", "save_prediction", "load_image", "read_image", "image_tensor",
                                        "ImageError", "Prediction", "decode_prediction", "MAX_IMAGE_PIXELS"),
    }  # fmt: skip
    evaluation = importlib.import_module("posediff.evaluation")
    for module, attrs in names.items():
        m = importlib.import_module(module)
        for name in attrs:
            obj = getattr(m, name)
            if hasattr(evaluation, name):
                assert obj is getattr(evaluation, name), (module, name)
    for gone in ("posediff.evaluate", "posediff.evaluate_bop", "posediff.report",
                 "posediff.module", "posediff.checkpoint", "posediff.regression", "posediff.tasks"):  # fmt: skip
        with pytest.raises(ModuleNotFoundError):
            importlib.import_module(gone)
    assert posediff.predict is importlib.import_module("posediff.evaluation.predict").predict
    assert not hasattr(posediff, "sample")


def test_a_regression_class_refuses_a_diffusion_checkpoint(ckpt: Path) -> None:
    """``load_from_checkpoint`` hands its own class to the loader as the expected base class."""
    from posediff.models import PoseRegressionModule

    with pytest.raises(CheckpointError, match="not a PoseRegressionModule"):
        PoseRegressionModule.load_from_checkpoint(ckpt)
