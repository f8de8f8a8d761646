"""Up-front checks of a BOP dataset's files: a broken copy of a small fixture is refused by
``BopDataModule.setup`` (or the reader) in one line naming the file, before any training."""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from posediff.data.bop.datamodule import BopDataModule
from posediff.data.bop.reader import BopFormatError, BopModels, BopSplit, read_depth, read_mask, read_rgb

STATS = {"mean": [0.0, 0.0, 1.0], "std": [1.0, 1.0, 1.0]}
W, H = 64, 48


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from posediff.data.bop.fixture import make_bop_fixture

    out = tmp_path_factory.mktemp("bop_validation") / "fixture"
    make_bop_fixture(out, seed=0, width=W, height=H, pbr_scenes=1, pbr_images=3, pbr_instances=2,
                     train_views=1, test_scenes=1, test_images=2, test_instances=2)  # fmt: skip
    return out


@pytest.fixture
def root(pristine: Path, tmp_path: Path) -> Path:
    """A fresh copy of the fixture, to break."""
    out = tmp_path / "bop"
    shutil.copytree(pristine, out)
    return out


def datamodule(root: Path, **kwargs: object) -> BopDataModule:
    return BopDataModule(str(root), image_size=16, min_visible_px=0, **kwargs)


def setup_error(root: Path, stage: str) -> str:
    """The one-line message of the error ``setup(stage)`` raises."""
    kwargs = {"translation_stats": STATS} if stage == "test" else {}
    with pytest.raises(BopFormatError) as info:
        datamodule(root, **kwargs).setup(stage)
    message = str(info.value)
    assert isinstance(info.value, ValueError) and "\n" not in message
    return message


def scene(root: Path, split: str) -> Path:
    return sorted(p for p in (root / split).iterdir() if p.is_dir())[0]


def image_ids(scene_dir: Path) -> list[int]:
    return sorted(int(k) for k in json.loads((scene_dir / "scene_gt.json").read_text()))


def png_header(path: Path, width: int, height: int) -> None:
    """A valid PNG whose header claims ``width`` x ``height`` RGB pixels (one tiny IDAT)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_the_pristine_fixture_passes(root: Path) -> None:
    dm = datamodule(root)
    dm.setup("fit")
    assert len(dm.train) and len(dm.test)
    assert all(i.image_hw == (H, W) for i in dm.train.instances)
    split = BopSplit(root, "test_primesense", BopModels(root))
    assert split.require_depth and split.evaluation
    assert not BopSplit(root, "train_pbr", BopModels(root)).require_depth


def test_a_missing_train_mask_is_named_with_the_count_of_others(root: Path) -> None:
    masks = sorted((scene(root, "train_pbr") / "mask_visib").glob("*.png"))
    assert len(masks) >= 5
    for m in masks[1:6]:
        m.unlink()
    name = masks[1].name
    im, g = int(name[:6]), int(name[7:13])
    msg = setup_error(root, "fit")
    assert msg.startswith(
        f"{masks[1]} is missing (scene 0 image {im} instance {g}; and 4 more files of train_pbr)"
    )
    assert msg.endswith("re-extract the split or drop the scene")


def test_a_missing_train_image_is_named(root: Path) -> None:
    sd = scene(root, "train_pbr")
    split = BopSplit(root, "train_pbr", BopModels(root))
    last = image_ids(sd)[-1]
    path = sd / "rgb" / f"{last:06d}.jpg"
    path.unlink()
    with pytest.raises(BopFormatError, match=rf"^{path} is missing \(scene 0 image {last}\)"):
        split.check_files()  # again, on demand
    assert setup_error(root, "fit").startswith(f"{path} is missing (scene 0 image {last})")


def test_grey_images_in_a_gray_folder_are_read(root: Path) -> None:
    """Grey-only BOP datasets (ITODD) keep their images in ``gray/``, not ``rgb/``."""
    sd = scene(root, "train_pbr")
    (sd / "rgb").rename(sd / "gray")
    dm = datamodule(root)
    dm.setup("fit")
    inst = [i for i in dm.train.instances if i.scene_id == int(sd.name)][0]
    assert inst.rgb_path.parent == sd / "gray" and dm.train[0]["image"].shape == (3, 16, 16)


def test_a_missing_test_depth_map_is_named_but_train_depth_is_not_needed(root: Path) -> None:
    for d in (scene(root, "train_pbr") / "depth").glob("*.png"):
        d.unlink()  # training needs no depth
    sd = scene(root, "test_primesense")
    path = sd / "depth" / f"{image_ids(sd)[-1]:06d}.png"
    path.unlink()
    with pytest.raises(BopFormatError, match="depth"):
        datamodule(root).setup("fit")  # fit also sets up the test split
    msg = setup_error(root, "test")
    assert msg.startswith(f"{path} is missing (scene {int(sd.name)} image {image_ids(sd)[-1]})")
    # a split can be read without its depth maps when the caller says so
    assert len(BopSplit(root, "test_primesense", BopModels(root), require_depth=False))


def test_a_test_image_of_the_wrong_size_is_refused(root: Path) -> None:
    sd = scene(root, "test_primesense")
    path = sd / "rgb" / f"{image_ids(sd)[0]:06d}.png"
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    cv2.imwrite(str(path), cv2.resize(img, (W // 2, H // 2)))
    msg = setup_error(root, "test")
    assert msg.startswith(f"{path} is {W // 2}x{H // 2} pixels, not {W}x{H} as camera_primesense.json says")
    assert "fix camera_primesense.json if the split was resized on purpose" in msg


def test_a_train_image_of_the_wrong_size_is_refused(root: Path) -> None:
    """No camera file for training splits (real T-LESS train_primesense is 400x400, its camera
    720x540): the size most of the split's images have."""
    sd = scene(root, "train_pbr")
    path = sd / "rgb" / f"{image_ids(sd)[0]:06d}.jpg"
    cv2.imwrite(str(path), np.zeros((H + 2, W, 3), np.uint8))
    msg = setup_error(root, "fit")
    assert msg.startswith(f"{path} is {W}x{H + 2} pixels, not {W}x{H} as most images of train_pbr are")


@pytest.mark.parametrize(
    ("folder", "value"),
    [("models_eval", v) for v in (None, 0.0, float("inf"), "wide")]
    + [("models", float("inf")), ("models", "wide")],
)  # models/ without a diameter, or with 0, was refused before these checks
def test_an_object_without_a_finite_positive_diameter_is_refused(
    root: Path, folder: str, value: object
) -> None:
    path = root / folder / "models_info.json"
    info = json.loads(path.read_text())
    if value is None:
        del info["2"]["diameter"]
    else:
        info["2"]["diameter"] = value
    path.write_text(json.dumps(info))
    with pytest.raises(BopFormatError) as e:
        datamodule(root).setup("fit")
    msg = str(e.value)
    assert msg.startswith(f"{path}: object 2 has ") and "diameter" in msg and "\n" not in msg


def test_truncated_images_are_named(root: Path) -> None:
    sd = scene(root, "test_primesense")
    path = sd / "rgb" / f"{image_ids(sd)[-1]:06d}.png"
    truncate(path)
    msg = setup_error(root, "test")
    assert msg.startswith(f"{path} is truncated (a PNG without its IEND chunk)")
    with pytest.raises(BopFormatError, match="is truncated"):
        read_rgb(path)
    sp = scene(root, "train_pbr")
    jpg = sp / "rgb" / f"{image_ids(sp)[-1]:06d}.jpg"
    truncate(jpg)  # OpenCV decodes half a JPEG without an error
    msg = setup_error(root, "fit")
    assert msg.startswith(f"{jpg} is truncated (a JPEG without its end-of-image marker)")


def test_a_truncated_train_mask_is_named_when_decoded(root: Path) -> None:
    """Training masks are only checked for presence up front (a million in T-LESS PBR); decoding
    one that is broken names it."""
    dm = datamodule(root)
    dm.setup("fit")
    inst = dm.train.instances[0]
    truncate(inst.mask_visib_path)
    with pytest.raises(BopFormatError, match=rf"^{inst.mask_visib_path} is truncated"):
        dm.train[0]
    with pytest.raises(ValueError, match="is truncated"):
        read_mask(inst.mask_visib_path)


@pytest.mark.parametrize("side", [10_000, 40_000])  # over PIL's warning limit, over its error limit
def test_a_decompression_bomb_is_refused_from_its_header(root: Path, side: int) -> None:
    sd = scene(root, "test_primesense")
    path = sd / "rgb" / f"{image_ids(sd)[0]:06d}.png"
    png_header(path, side, side)
    msg = setup_error(root, "test")
    assert msg.startswith(f"{path} is over PIL's decompression-bomb limit (")
    with pytest.raises(BopFormatError, match="decompression-bomb"):
        read_rgb(path)


def test_depth_must_be_16_bit(root: Path) -> None:
    sd = scene(root, "test_primesense")
    path = sd / "depth" / f"{image_ids(sd)[0]:06d}.png"
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16  # the fixture's (and BOP's) depth maps
    cv2.imwrite(str(path), (depth // 256).astype(np.uint8))
    msg = setup_error(root, "test")
    assert msg.startswith(f"{path} is a PNG of mode L, not a 16-bit grey PNG")
    with pytest.raises(BopFormatError, match="not a 16-bit grey PNG"):
        read_depth(path, 0.1)


def test_an_odd_colour_mode_is_refused(root: Path) -> None:
    sd = scene(root, "train_pbr")
    path = sd / "rgb" / f"{image_ids(sd)[-1]:06d}.jpg"
    Image.new("CMYK", (W, H)).save(path)
    msg = setup_error(root, "fit")
    assert msg.startswith(f"{path} is a JPEG of mode CMYK, which cannot be read as a colour image")
    with pytest.raises(BopFormatError, match="mode CMYK"):
        read_rgb(path)


def test_16_bit_colour_and_grey_images_keep_working(root: Path) -> None:
    """BOP's 16-bit colour or grey images are read as 8-bit (OpenCV keeps the high byte); a regression
    guard (it held before the checks too)."""
    sd = scene(root, "test_primesense")
    first, second = (sd / "rgb" / f"{i:06d}.png" for i in image_ids(sd))
    rgb8 = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in (first, second)]
    cv2.imwrite(str(first), rgb8[0].astype(np.uint16) * 257)
    grey = cv2.cvtColor(rgb8[1], cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(second), grey.astype(np.uint16) * 257)
    dm = datamodule(root, translation_stats=STATS)
    dm.setup("test")
    assert len(dm.test) and dm.test[0]["image"].shape == (3, 16, 16)
    assert np.array_equal(read_rgb(first), cv2.cvtColor(rgb8[0], cv2.COLOR_BGR2RGB))
    assert np.array_equal(read_rgb(second), np.repeat(grey[..., None], 3, axis=2))
