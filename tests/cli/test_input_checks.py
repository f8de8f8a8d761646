"""Input checks at the edges a user touches first: image files (EXIF orientation, folders, devices,
``~``), the Python API ``posediff.predict`` (layouts, dtypes, ranges, non-finite pixels or weights,
bad numeric arguments) and BOP19 results files (rotations that are none, a byte-order mark, other
encodings). Each refusal is one line, of a posediff ``ValueError`` / ``OSError`` subclass, so the
CLI prints it as ``posediff <command>: ...``."""

from __future__ import annotations

import copy
import inspect
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.testing import assert_close

import posediff
from posediff.cli import input_error_line
from posediff.evaluation.predict import (
    ImageError,
    ImageNotFoundError,
    NonFiniteWeightsError,
    PredictArgumentError,
    check_finite_weights,
    load_image,
    read_image,
)
from posediff.metrics.bop19 import (
    ROTATION_TOLERANCE,
    BopEstimate,
    BopResultsError,
    read_bop19_csv,
)

pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")

SIZE = 32


def tiny_model() -> torch.nn.Module:
    """A tiny untrained locate-then-crop image model (its crop goes through torchvision's roi_align)."""
    import torch

    from posediff.diffusion import ConcentratedGaussian, Diffusion, FewStepSampler, PowerSchedule
    from posediff.lie import get_group
    from posediff.models import PoseDiffusionModule
    from posediff.nn import MLPDenoiser, PoseEncoder

    torch.manual_seed(0)
    diffusion = Diffusion(ConcentratedGaussian(get_group("se3")), PowerSchedule())
    encoder = PoseEncoder(image_size=32, crop_size=16, out_dim=8)
    denoiser = MLPDenoiser(8, 6, 6, hidden_dim=8, num_frequencies=4, time_dim=8)
    return PoseDiffusionModule(diffusion, denoiser, FewStepSampler, encoder=encoder, cond_key="image").eval()


def _one_line(e: BaseException) -> str:
    """The line the CLI prints for ``e``; fails unless posediff defines its class (ValueError/OSError)."""
    line = input_error_line(e)
    assert line is not None, f"{type(e).__module__}.{type(e).__name__} is not a posediff input error"
    assert "\n" not in str(e).strip(), str(e)
    return line


# --------------------------------------------------------------------------------------------------
# Image files
# --------------------------------------------------------------------------------------------------


def _upright() -> np.ndarray:
    """An image whose orientation is plain to see: a red top band and a green left band on a smooth
    blue gradient (smooth, so JPEG keeps it close)."""
    y, x = np.mgrid[0:SIZE, 0:SIZE]
    img = np.zeros((SIZE, SIZE, 3), np.uint8)
    img[..., 2] = (4 * y + 2 * x).astype(np.uint8)
    img[:8, :, 0] = 255
    img[:, :6, 1] = 255
    return img


@pytest.mark.parametrize("orientation", [6, 8])
def test_exif_orientation_is_applied(orientation: int, tmp_path: Path) -> None:
    """A phone's JPEG stores the sensor's pixels and an Orientation tag: 6 = turn 90° clockwise to
    view, 8 = 90° counter-clockwise. The image read is the upright one, the way a viewer shows it."""
    from PIL import Image

    up = _upright()
    # what the camera stores: the upright picture turned the other way
    stored = np.rot90(up, 1 if orientation == 6 else -1).copy()
    exif = Image.Exif()
    exif[0x0112] = orientation
    tagged, plain = tmp_path / "tagged.jpg", tmp_path / "plain.jpg"
    Image.fromarray(stored).save(tagged, quality=100, subsampling=0, exif=exif.tobytes())
    Image.fromarray(stored).save(plain, quality=100, subsampling=0)  # the same JPEG data, no tag
    decoded = np.asarray(Image.open(plain).convert("RGB"))

    got = np.asarray(read_image(tagged))
    expected = np.rot90(decoded, -1 if orientation == 6 else 1)  # exactly the stored pixels, turned
    np.testing.assert_array_equal(got, expected)
    assert np.abs(got.astype(int) - up).mean() < 3 < np.abs(decoded.astype(int) - up).mean()
    # load_image (the model's input) and image_tensor on a PIL image opened by hand agree
    t = load_image(tagged, SIZE)
    assert_close(t, torch.from_numpy(expected.transpose(2, 0, 1).astype(np.float32) / 255.0))
    from posediff.evaluation.predict import image_tensor

    assert_close(image_tensor(Image.open(tagged), SIZE), t)
    # a second pass does not turn it again
    assert_close(image_tensor(read_image(tagged), SIZE), t)


def test_a_folder_as_image_is_called_a_folder(tmp_path: Path) -> None:
    with pytest.raises(ImageError, match="is a folder, not an image file") as e:
        read_image(tmp_path)
    assert str(tmp_path) in _one_line(e.value)


@pytest.mark.parametrize("device", ["/dev/null", "/dev/zero"])
def test_a_device_as_image_is_not_a_regular_file(device: str) -> None:
    if not Path(device).exists():
        pytest.skip(f"no {device} here")
    with pytest.raises(ImageError, match="is not a regular file") as e:
        load_image(device, SIZE)
    assert device in _one_line(e.value)


def test_a_missing_image_is_not_found_as_a_posediff_error(tmp_path: Path) -> None:
    with pytest.raises(ImageNotFoundError, match="not found") as e:
        read_image(tmp_path / "none.png")
    assert isinstance(e.value, FileNotFoundError)
    _one_line(e.value)


def test_tilde_is_expanded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from PIL import Image

    monkeypatch.setenv("HOME", str(tmp_path))
    Image.fromarray(_upright()).save(tmp_path / "photo.png")
    np.testing.assert_array_equal(np.asarray(read_image("~/photo.png")), _upright())
    assert_close(load_image(Path("~") / "photo.png", SIZE), load_image(tmp_path / "photo.png", SIZE))
    with pytest.raises(ImageNotFoundError, match=f"image {tmp_path / 'nope.png'} not found"):
        read_image("~/nope.png")


# --------------------------------------------------------------------------------------------------
# The Python API: posediff.predict
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model() -> torch.nn.Module:
    return tiny_model()


@pytest.fixture(scope="module")
def image() -> torch.Tensor:
    return torch.rand(3, SIZE, SIZE, generator=torch.Generator().manual_seed(0))


def _sample(model: torch.nn.Module, image: object, **kw: object) -> torch.Tensor:
    return posediff.predict(model, image, num_samples=kw.pop("num_samples", 4), **kw).samples


def test_a_batch_of_one_is_one_image(model: torch.nn.Module, image: torch.Tensor) -> None:
    assert_close(_sample(model, image[None]), _sample(model, image))
    # whole numbers of any integer type, and ints for the float settings, are fine
    pred = posediff.predict(
        model, image[None], num_samples=np.int64(3), seed=7, mode_radius_deg=5, min_mode_weight=0
    )
    assert pred.samples.shape == (3, 4, 4) and torch.isfinite(pred.samples).all()


def test_a_batch_of_several_is_refused_with_what_to_do(model: torch.nn.Module, image: torch.Tensor) -> None:
    with pytest.raises(ImageError, match="batch of 2 images.*call it once per image") as e:
        _sample(model, torch.stack([image, image]))
    _one_line(e.value)


def test_float64_is_converted(model: torch.nn.Module, image: torch.Tensor) -> None:
    assert_close(_sample(model, image.double()), _sample(model, image))


def test_uint8_is_scaled_by_1_over_255(model: torch.nn.Module, image: torch.Tensor) -> None:
    u8 = (image * 255).round().to(torch.uint8)
    assert_close(_sample(model, u8), _sample(model, u8.float() / 255.0))


def test_a_0_255_float_image_is_refused_with_the_hint(model: torch.nn.Module, image: torch.Tensor) -> None:
    with pytest.raises(ImageError, match=r"not \[0, 1\]; it looks like 0–255: divide it by 255") as e:
        _sample(model, image * 255)
    _one_line(e.value)
    with pytest.raises(ImageError, match="normalised"):  # ImageNet mean/std
        _sample(model, (image - 0.45) / 0.225)
    # rounding / resampling overshoot of under one grey level is accepted
    _sample(model, (image * 1.002).clamp(max=1.003))


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (lambda x: x.permute(1, 2, 0), "channels-last"),
        (lambda x: x[0], "grey"),
        (lambda x: x[:, :16, :16], "this model takes 32×32"),
        (lambda x: (x * 255).long(), "torch.int64 pixels"),
        (lambda x: x > 0.5, "torch.bool pixels"),
        (lambda x: x.tolist(), "must be a \\(3, H, W\\) tensor"),
    ],
)
def test_other_layouts_and_dtypes_are_refused(
    model: torch.nn.Module, image: torch.Tensor, bad: object, message: str
) -> None:
    with pytest.raises(ImageError, match=message) as e:
        _sample(model, bad(image))
    _one_line(e.value)


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"num_samples": 0}, "num_samples must be a whole number ≥ 1, got 0"),
        ({"num_samples": -3}, "num_samples must be a whole number ≥ 1, got -3"),
        ({"num_samples": 2.5}, "num_samples must be a whole number"),
        ({"num_samples": True}, "num_samples must be a whole number"),
        ({"seed": 1.5}, "seed must be a whole number"),
        ({"mode_radius_deg": 0.0}, "mode_radius_deg must be finite and > 0"),
        ({"mode_radius_deg": -10.0}, "mode_radius_deg must be finite and > 0"),
        ({"mode_radius_deg": float("nan")}, "mode_radius_deg must be finite and > 0"),
        ({"mode_radius_deg": float("inf")}, "mode_radius_deg must be finite and > 0"),
        ({"min_mode_weight": -0.1}, r"min_mode_weight must be in \[0, 1\)"),
        ({"min_mode_weight": 1.0}, r"min_mode_weight must be in \[0, 1\)"),
        ({"min_mode_weight": float("nan")}, r"min_mode_weight must be in \[0, 1\)"),
        ({"trajectory": "no"}, "trajectory must be True or False"),
    ],
)
def test_bad_numeric_arguments_are_refused(
    model: torch.nn.Module, image: torch.Tensor, kw: dict, message: str
) -> None:
    with pytest.raises(PredictArgumentError, match=message) as e:
        _sample(model, image, **kw)
    _one_line(e.value)


def test_non_finite_weights_are_named(model: torch.nn.Module, image: torch.Tensor) -> None:
    """The first non-finite parameter is named (the denoiser's here: NaN there gives NaN samples, not
    a crash; NaN in the locator is the subprocess test below)."""
    bad = copy.deepcopy(model)
    name, param = next((n, p) for n, p in bad.named_parameters() if n.startswith("denoiser."))
    with torch.no_grad():
        param.view(-1)[:2] = torch.tensor([float("inf"), float("nan")])
    with pytest.raises(
        NonFiniteWeightsError, match=f"the model: parameter {name} has 2 non-finite values"
    ) as e:
        _sample(bad, image)
    _one_line(e.value)
    # a buffer (batch-norm statistics) too; the check is public (the checkpoint loader calls it)
    bn = copy.deepcopy(model)
    name, buf = next((n, b) for n, b in bn.named_buffers() if n.endswith("running_var"))
    buf.fill_(float("nan"))
    with pytest.raises(NonFiniteWeightsError, match=f"ckpt.pt: buffer {name} has {buf.numel()} non-finite"):
        check_finite_weights(bn, "ckpt.pt")
    check_finite_weights(model, "ckpt.pt")  # finite weights pass


CRASH_SCRIPT = (
    "import torch\nimport posediff\n"
    + inspect.getsource(tiny_model)
    + textwrap.dedent(
        """
        model = tiny_model()
        image = torch.rand(3, 32, 32)
        one_inf = image.clone()
        one_inf[1, 3, 4] = float("inf")
        for what, x in (("NaN image", torch.full_like(image, float("nan"))), ("one inf pixel", one_inf)):
            try:
                posediff.predict(model, x, num_samples=2)
                print(f"{what}: no error", flush=True)
            except ValueError as e:
                print(f"{what}: {type(e).__name__}: {e}", flush=True)
        with torch.no_grad():
            next(model.encoder.locator.parameters()).fill_(float("nan"))
        try:
            posediff.predict(model, image, num_samples=2)
            print("NaN locator: no error", flush=True)
        except ValueError as e:
            print(f"NaN locator: {type(e).__name__}: {e}", flush=True)
        """
    )
)


def test_nan_image_or_weights_are_an_error_not_a_crash(tmp_path: Path) -> None:
    """A NaN image or NaN locator weights gave NaN crop boxes, and roi_align killed the process
    (exit −11, nothing printed): a subprocess, so that a crash fails this test, not the suite."""
    proc = subprocess.run([sys.executable, "-c", CRASH_SCRIPT], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path, env={**os.environ, "PYTHONFAULTHANDLER": "1"})  # fmt: skip
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr[-3000:]}"
    lines = proc.stdout.splitlines()
    assert (
        "NaN image: ImageError: image has 3072 non-finite pixel values (NaN or ±inf) of 3072" in proc.stdout
    ), lines
    assert "one inf pixel: ImageError: image has 1 non-finite pixel value (NaN or ±inf)" in proc.stdout, lines
    assert "NaN locator: NonFiniteWeightsError: the model: parameter encoder.locator." in proc.stdout, lines


# --------------------------------------------------------------------------------------------------
# BOP19 results files
# --------------------------------------------------------------------------------------------------

HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def _rotation() -> np.ndarray:
    from posediff.lie import SO3

    return SO3().sample_uniform((1,), generator=torch.Generator().manual_seed(3))[0].double().numpy()


def _row(R: np.ndarray, fmt: str = "{!r}") -> str:
    return f"1,3,2,0.9,{' '.join(fmt.format(float(x)) for x in R.reshape(-1))},10.5 -3.25 700,0.25"


def _csv(tmp_path: Path, *rows: str, data: bytes | None = None) -> Path:
    path = tmp_path / "method_bop-test.csv"
    path.write_bytes(data if data is not None else ("\n".join([HEADER, *rows]) + "\n").encode())
    return path


@pytest.mark.parametrize(
    ("R", "message"),
    [
        (lambda R: 2 * R, "R looks like a rotation scaled by 2 "),
        (lambda R: 1.01 * R, "R looks like a rotation scaled by 1.01 "),
        (lambda R: R @ np.diag([1.0, 1.0, -1.0]), "R has det -1 \\(a reflection"),
        (lambda R: -R, "R has det -1 \\(a reflection"),
        (lambda R: np.zeros((3, 3)), "R is all zeros"),
        (lambda R: R + np.outer([0, 0, 1], [0.1, 0, 0]), "R is not orthonormal"),
    ],
)
def test_a_rotation_that_is_none_is_refused_with_file_and_line(
    tmp_path: Path, R: object, message: str
) -> None:
    good = _rotation()
    path = _csv(tmp_path, _row(good, "{:.6g}"), _row(R(good)))  # line 2 passes, line 3 does not
    with pytest.raises(BopResultsError, match=f"method_bop-test.csv:3: {message}") as e:
        read_bop19_csv(path)
    assert f"within {ROTATION_TOLERANCE:g}" in _one_line(e.value)


def test_the_tolerance_takes_rounded_results_and_refuses_a_slight_scale(tmp_path: Path) -> None:
    """Full precision, float32's 9 digits, 6 digits and 4 decimals all stay inside the tolerance
    (what is read is what was written); R scaled by 1.0003 (RᵀR − I = 6e-4, det − 1 = 9e-4) passes, by 1.0006
    (1.2e-3) does not."""
    good = _rotation()
    for fmt in ("{!r}", "{:.9g}", "{:.6g}", "{:.4f}"):
        (e,) = read_bop19_csv(_csv(tmp_path, _row(good, fmt)))
        assert_close(e.R, good, atol=6e-5, rtol=0)
    read_bop19_csv(_csv(tmp_path, _row(1.0003 * good)))
    with pytest.raises(
        BopResultsError, match="method_bop-test.csv:2: R looks like a rotation scaled by 1.0006"
    ):
        read_bop19_csv(_csv(tmp_path, _row(1.0006 * good)))


def test_a_byte_order_mark_is_accepted(tmp_path: Path) -> None:
    good = _rotation()
    text = "\n".join([HEADER, _row(good)]) + "\n"
    plain = read_bop19_csv(_csv(tmp_path, data=text.encode()))
    with_bom = read_bop19_csv(_csv(tmp_path, data=text.encode("utf-8-sig")))
    assert with_bom == plain and len(plain) == 1
    # also without a header line
    assert read_bop19_csv(_csv(tmp_path, data=("\ufeff" + _row(good) + "\n").encode())) == plain


def test_a_file_not_in_utf8_is_named_with_line_and_byte(tmp_path: Path) -> None:
    good = _rotation()
    text = "\n".join([HEADER, _row(good), "# méthode"]) + "\n"
    path = _csv(tmp_path, data=text.encode("latin-1"))
    with pytest.raises(
        BopResultsError, match=r"method_bop-test.csv:3: not UTF-8 text \(byte 0xe9 at column 4\)"
    ) as e:
        read_bop19_csv(path)
    assert str(path) in _one_line(e.value)
    # Windows' "Unicode" (UTF-16, with its own byte-order mark)
    with pytest.raises(
        BopResultsError, match=r"method_bop-test.csv:1: not UTF-8 text \(byte 0xff at column 1\)"
    ):
        read_bop19_csv(_csv(tmp_path, data=text.encode("utf-16")))


def test_check_estimates_refuses_a_scaled_rotation(bop_root: Path) -> None:
    """Estimates built in Python (not read from a file) are checked by ``check_estimates`` too; the
    ground truth itself passes."""
    from posediff.data.bop import BopDataModule
    from posediff.evaluation.bop import check_estimates

    dm = BopDataModule(str(bop_root), image_size=32, batch_size=2, num_workers=0, augment=None)
    dm.read_targets()
    rows = [BopEstimate(i.scene_id, i.im_id, i.obj_id, 1.0, i.R, i.t, 0.5) for i in dm.targets]
    check_estimates(rows, dm)
    rows[1] = BopEstimate(rows[1].scene_id, rows[1].im_id, rows[1].obj_id, 1.0, 2 * rows[1].R, rows[1].t, 0.5)
    with pytest.raises(BopResultsError, match="row 2: R looks like a rotation scaled by 2 ") as e:
        check_estimates(rows, dm)
    _one_line(e.value)
