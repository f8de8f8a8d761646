"""The benchmarks' own files (issue 28): official SYMSOL I/II (unpacked zip, tfds TFRecords) and the
authors' SYMSOL-T, on tiny fixtures rendered by posediff (nothing is downloaded)."""

from __future__ import annotations

import gzip
import json
import os
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from posediff.cli import main
from posediff.data.official import (
    OfficialDataError,
    SymsolOfficialDataModule,
    SymsoltOfficialDataModule,
    TFRecordError,
    TFRecordFile,
    UnsafePickleError,
    encode_example,
    load_plain_pickle,
    model_frame,
    parse_example,
    quaternion_wxyz_to_matrix,
    to_posediff,
    to_theirs,
    write_tfrecord,
)
from posediff.data.official.fixture import make_symsol_fixture, make_symsolt_fixture
from posediff.data.official.symsolt import matrix_to_quaternion_wxyz
from posediff.data.official.tfrecord import crc32c
from posediff.symmetry import GOLDEN_RATIO, SHAPES, SYMSOL_LABELS

ALL = list(SYMSOL_LABELS)


@pytest.fixture(scope="module")
def symsol_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_symsol_fixture(tmp_path_factory.mktemp("symsol") / "zip", layout="zip", n_per_shape=3)


@pytest.fixture(scope="module")
def symsol_tfds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_symsol_fixture(tmp_path_factory.mktemp("symsol") / "tfds", layout="tfds", n_per_shape=3)


@pytest.fixture(scope="module")
def symsolt_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_symsolt_fixture(tmp_path_factory.mktemp("symsolt") / "authors", n_per_shape=3, image_size=128)


# ----------------------------------------------------------------------------- TFRecord
def test_crc32c_check_value() -> None:
    assert crc32c(b"123456789") == 0xE3069283  # the CRC-32C catalogue's check value


def test_example_round_trip_and_unpacked_floats(tmp_path: Path) -> None:
    ex = {"image": b"\x89PNG", "label_shape": np.array([6]), "neg": np.array([-3, 2**40]),
          "rotation": np.arange(9, dtype=np.float32) / 7}  # fmt: skip
    got = parse_example(encode_example(ex))
    assert got["image"] == [b"\x89PNG"]
    np.testing.assert_array_equal(got["label_shape"], [6])
    np.testing.assert_array_equal(got["neg"], [-3, 2**40])
    np.testing.assert_array_equal(got["rotation"], ex["rotation"])
    # a FloatList written unpacked (one fixed32 per value, as some writers do)
    vals = b"".join(b"\x0d" + struct.pack("<f", v) for v in (1.5, -2.0))
    flist = b"\x0a" + bytes([len(vals)]) + vals  # Feature.float_list = 2 … wrapped below
    feature = b"\x12" + bytes([len(vals)]) + vals
    entry = b"\x0a\x01x" + b"\x12" + bytes([len(feature)]) + feature
    features = b"\x0a" + bytes([len(entry)]) + entry
    example = b"\x0a" + bytes([len(features)]) + features
    del flist
    np.testing.assert_array_equal(parse_example(example)["x"], [1.5, -2.0])
    path = tmp_path / "a.tfrecord"
    write_tfrecord(path, [encode_example(ex), b"second"])
    f = TFRecordFile(path)
    assert len(f) == 2 and f.read(1, verify=True) == b"second"


def test_tfrecord_damage_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "a.tfrecord"
    write_tfrecord(path, [b"x" * 100])
    data = path.read_bytes()
    (tmp_path / "short.tfrecord").write_bytes(data[:50])
    with pytest.raises(TFRecordError, match="truncated record"):
        TFRecordFile(tmp_path / "short.tfrecord")
    (tmp_path / "junk.tfrecord").write_bytes(b"not a tfrecord at all")
    with pytest.raises(TFRecordError, match="not a TFRecord file"):
        TFRecordFile(tmp_path / "junk.tfrecord")
    bad = bytearray(data)
    bad[20] ^= 0xFF
    (tmp_path / "flip.tfrecord").write_bytes(bytes(bad))
    with pytest.raises(TFRecordError, match="damaged"):
        TFRecordFile(tmp_path / "flip.tfrecord").read(0, verify=True)


# ----------------------------------------------------------------------------- the unpickler
class _Payload:
    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):  # noqa: ANN204
        return (os.system, (f"touch {self.target}",))


def test_plain_pickle_reads_plain_data(tmp_path: Path) -> None:
    data = [{"rotation": [1.0, 0.0, 0.0, 0.0], "label_shape": 3, "image": "cone/images/000000.png",
             "t": (1, 2), "none": None, "ok": True, "x": -1.5e-300}]  # fmt: skip
    for protocol in range(pickle.HIGHEST_PROTOCOL + 1):
        path = tmp_path / f"p{protocol}.gz"
        path.write_bytes(gzip.compress(pickle.dumps(data, protocol=protocol)))
        assert load_plain_pickle(path) == data


@pytest.mark.parametrize("protocol", [0, 2, pickle.HIGHEST_PROTOCOL])
def test_plain_pickle_refuses_a_payload_and_runs_nothing(tmp_path: Path, protocol: int) -> None:
    target = tmp_path / "pwned"
    path = tmp_path / "annotations.gz"
    path.write_bytes(gzip.compress(pickle.dumps([{"image": "x.png"}, _Payload(target)], protocol=protocol)))
    with pytest.raises(UnsafePickleError) as info:
        load_plain_pickle(path)
    msg = str(info.value)
    assert (
        len(msg.splitlines()) == 1 and str(path) in msg and "system" in msg and "nothing in it was run" in msg
    )
    assert not target.exists()
    # a numpy array is a class too
    path.write_bytes(gzip.compress(pickle.dumps([np.zeros(3)], protocol=protocol)))
    with pytest.raises(UnsafePickleError, match="numpy"):
        load_plain_pickle(path)


def test_plain_pickle_bad_files(tmp_path: Path) -> None:
    raw = tmp_path / "annotations.gz"
    raw.write_bytes(pickle.dumps([1, 2]))
    with pytest.raises(UnsafePickleError, match="not a gzip file"):
        load_plain_pickle(raw)
    raw.write_bytes(gzip.compress(pickle.dumps(list(range(1000))))[:-30])
    with pytest.raises(UnsafePickleError, match="truncated"):
        load_plain_pickle(raw)
    raw.write_bytes(gzip.compress(b"definitely not a pickle"))
    with pytest.raises(UnsafePickleError, match="not a readable pickle"):
        load_plain_pickle(raw)


# ----------------------------------------------------------------------------- SYMSOL
@pytest.mark.parametrize("layout", ["zip", "tfds"])
def test_symsol_official_batches(layout: str, symsol_zip: Path, symsol_tfds: Path) -> None:
    root = symsol_zip if layout == "zip" else symsol_tfds
    dm = SymsolOfficialDataModule(str(root), shapes=ALL, image_size=32, batch_size=4, group="so3")
    dm.setup("fit")
    assert dm.layout == layout
    assert len(dm.train) + len(dm.val) == 3 * len(ALL) and len(dm.test) == 3 * len(ALL)
    batch = next(iter(dm.train_dataloader()))
    for key in (
        "image",
        "pose",
        "rotation",
        "translation",
        "shape",
        "index",
        "symmetries",
        "symmetries_mask",
    ):
        assert key in batch
    assert batch["image"].shape == (4, 3, 32, 32) and batch["pose"].shape == (4, 3, 3)
    # the files' equivalents are posediff's groups for SYMSOL I; the marked shapes have the truth alone
    agree = dm.symmetry_agreement()
    assert set(agree) == set(SHAPES) and max(agree.values()) < 1e-3
    sizes = {s: len(dm.symmetry_sets[s]) for s in ALL}
    assert sizes == {
        "tet": 12,
        "cube": 24,
        "icosa": 60,
        "cone": 360,
        "cyl": 720,
        "tetX": 1,
        "cylO": 1,
        "sphereX": 1,
    }
    # every sample's padded symmetries are its shape's set
    for i in range(len(batch["shape"])):
        name = SYMSOL_LABELS[int(batch["shape"][i])]
        assert int(batch["symmetries_mask"][i].sum()) == sizes[name]


def test_symsol_official_bad_inputs(tmp_path: Path) -> None:
    root = make_symsol_fixture(tmp_path / "zip", layout="zip", n_per_shape=2, shapes=["tet", "cube"])
    with pytest.raises(OfficialDataError, match="neither official SYMSOL layout"):
        SymsolOfficialDataModule(str(tmp_path), group="so3")
    with pytest.raises(OfficialDataError, match="no such folder"):
        SymsolOfficialDataModule(str(tmp_path / "absent"), group="so3")
    with pytest.raises(OfficialDataError, match="use group=so3"):
        SymsolOfficialDataModule(str(root), group="se3")
    with pytest.raises(OfficialDataError, match=r"no rotations for icosa .*set data.shapes"):
        SymsolOfficialDataModule(str(root), shapes=["tet", "icosa"], group="so3").setup("test")
    (root / "test" / "images" / "cube_00001.png").unlink()
    with pytest.raises(OfficialDataError, match=r"1 cube images but 2 rotations"):
        SymsolOfficialDataModule(str(root), shapes=["cube"], group="so3").setup("test")
    png = root / "test" / "images" / "tet_00001.png"
    png.write_bytes(png.read_bytes()[:60])
    dm = SymsolOfficialDataModule(str(root), shapes=["tet"], image_size=32, group="so3")
    dm.setup("test")
    with pytest.raises(OfficialDataError, match=r"tet_00001.png: not a readable image"):
        dm.test[1]
    # a file of camera → object rotations (equivalents S·R) is read transposed: the same poses
    z = dict(np.load(root / "train" / "rotations.npz"))
    truth = torch.from_numpy(z["tet"][:, 0].copy())
    np.savez(root / "train" / "rotations.npz", **{**z, "tet": z["tet"].swapaxes(-1, -2)})
    dm = SymsolOfficialDataModule(str(root), shapes=["tet"], image_size=32, group="so3")
    dm.setup("fit")
    got = torch.stack(
        [dm.train[i]["rotation"] for i in range(len(dm.train))]
        + [dm.val[i]["rotation"] for i in range(len(dm.val))]
    )
    torch.testing.assert_close(got, truth)
    # equivalents that are not one symmetry set at all
    z["tet"] = np.einsum("kij,nkjl->nkil", z["tet"][0], z["tet"])
    np.savez(root / "train" / "rotations.npz", **z)
    with pytest.raises(OfficialDataError, match="not one symmetry set"):
        SymsolOfficialDataModule(str(root), shapes=["tet"], group="so3").setup("fit")


def test_symsol_tfds_found_from_its_parents(symsol_tfds: Path) -> None:
    for root in (symsol_tfds, symsol_tfds.parent, symsol_tfds.parent.parent):
        assert SymsolOfficialDataModule(str(root), group="so3").layout == "tfds"
    info = json.loads((symsol_tfds / "dataset_info.json").read_text())
    assert info["name"] == "symmetric_solids"


# ----------------------------------------------------------------------------- SYMSOL-T
def test_quaternions_round_trip() -> None:
    rng = np.random.default_rng(0)
    q = rng.standard_normal((50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = quaternion_wxyz_to_matrix(q)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(matrix_to_quaternion_wxyz(R)), R, atol=1e-12)
    # wxyz: (cos θ/2, sin θ/2 · axis) is a rotation by θ about the axis
    Rz = quaternion_wxyz_to_matrix([np.cos(0.25), 0.0, 0.0, np.sin(0.25)])
    np.testing.assert_allclose(
        Rz, [[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]], atol=1e-12
    )


def test_model_frames_match_the_authors_meshes() -> None:
    """C maps posediff's solids onto the authors' Open3D ones (their vertex lists, written out here
    independently of the reader), and o moves posediff's cone origin (centre of mass, h/4 above the
    base) to theirs (the vertex mean of base centre, tip and 360 rim points: h/362 above the base)."""
    from posediff.data.symsol.shapes import make_mesh

    r = np.sqrt
    theirs = {
        "tet": np.array([(r(8 / 9), 0, -1 / 3), (-r(2 / 9), r(2 / 3), -1 / 3), (-r(2 / 9), -r(2 / 3), -1 / 3), (0, 0, 1)]),
        "icosa": np.array([(-1, 0, GOLDEN_RATIO), (1, 0, GOLDEN_RATIO), (1, 0, -GOLDEN_RATIO), (-1, 0, -GOLDEN_RATIO),
                           (0, -GOLDEN_RATIO, 1), (0, GOLDEN_RATIO, 1), (0, GOLDEN_RATIO, -1), (0, -GOLDEN_RATIO, -1),
                           (-GOLDEN_RATIO, -1, 0), (GOLDEN_RATIO, -1, 0), (GOLDEN_RATIO, 1, 0), (-GOLDEN_RATIO, 1, 0)]),
    }  # fmt: skip
    for shape, v in theirs.items():
        C, o = model_frame(shape)
        mine = np.asarray(make_mesh(shape).vertices)
        mine = mine / np.linalg.norm(mine, axis=1, keepdims=True)
        v = v / np.linalg.norm(v, axis=1, keepdims=True)
        assert np.allclose(o, 0) and np.isclose(np.linalg.det(C), 1.0)
        assert np.abs((mine @ C.T) @ v.T).max(1).min() > 1 - 1e-9  # every mapped vertex is one of theirs
    C, o = model_frame("cone")
    mine = np.asarray(make_mesh("cone").vertices)
    h = 3.5
    assert np.isclose(mine[:, 2].min() + o[2], -h / 362) and np.isclose(mine[:, 2].max() + o[2], h - h / 362)
    for shape in ("cube", "cyl"):
        C, o = model_frame(shape)
        assert np.allclose(C, np.eye(3)) and np.allclose(o, 0)
    rng = np.random.default_rng(1)
    R = quaternion_wxyz_to_matrix(rng.standard_normal(4))
    t = rng.uniform(-1, 1, 3)
    for shape in SHAPES:
        R2, t2 = to_posediff(shape, *to_theirs(shape, R, t))
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)


def test_symsolt_official_conventions_by_silhouette(symsolt_root: Path) -> None:
    """posediff's mesh rendered at the converted pose has the silhouette of the image the record
    names (IoU 1 up to a few edge pixels); without the frame conversion the tetrahedron and
    icosahedron do not."""
    from posediff.data.symsol import SymsolRenderer

    dm = SymsoltOfficialDataModule(str(symsolt_root), image_size=128, group="se3")
    dm.setup("test")
    agree = dm.symmetry_agreement()
    assert set(agree) == set(SHAPES) and max(agree.values()) < 1e-3
    renderer = SymsolRenderer(128)
    try:
        worst, unconverted = 1.0, {}
        for i in range(len(dm.test)):
            s = dm.test[i]
            shape = SHAPES[int(s["shape"])]
            cam = s["camera_pose"].double().numpy()
            image = s["image"].mean(0).numpy() > 0
            mask = renderer(shape, cam[:3, :3], cam[:3, 3]).rgb.mean(-1) > 0
            worst = min(worst, (mask & image).sum() / (mask | image).sum())
            C, _ = model_frame(shape)
            raw = renderer(shape, cam[:3, :3] @ C.T, cam[:3, 3]).rgb.mean(-1) > 0
            unconverted.setdefault(shape, []).append((raw & image).sum() / (raw | image).sum())
    finally:
        renderer.close()
    assert worst > 0.98
    assert max(unconverted["tet"]) < 0.8 and max(unconverted["icosa"]) < 0.97
    np.testing.assert_allclose(dm.test[0]["pose"][:3, 3], dm.test[0]["translation"])


def test_symsolt_official_bad_inputs(tmp_path: Path) -> None:
    root = make_symsolt_fixture(tmp_path / "authors", n_per_shape=2, shapes=["cube"], image_size=32)
    with pytest.raises(OfficialDataError, match="no test\\* folder with annotations.gz"):
        SymsoltOfficialDataModule(str(tmp_path), shapes=["cube"]).setup("test")
    test_dir = next(root.glob("test-*"))
    ann = test_dir / "annotations.gz"
    good = ann.read_bytes()
    ann.write_bytes(gzip.decompress(good))
    with pytest.raises(OfficialDataError, match="not a gzip file"):
        SymsoltOfficialDataModule(str(root), shapes=["cube"]).setup("test")
    target = tmp_path / "pwned"
    ann.write_bytes(gzip.compress(pickle.dumps([_Payload(target)])))
    with pytest.raises(OfficialDataError, match="refused"):
        SymsoltOfficialDataModule(str(root), shapes=["cube"]).setup("test")
    assert not target.exists()
    records = pickle.loads(gzip.decompress(good))
    ann.write_bytes(gzip.compress(pickle.dumps([{k: v for k, v in records[0].items() if k != "rotation"}])))
    with pytest.raises(OfficialDataError, match="record 0: needs image, rotation"):
        SymsoltOfficialDataModule(str(root), shapes=["cube"]).setup("test")
    ann.write_bytes(good)
    (test_dir / records[1]["image"]).unlink()
    with pytest.raises(OfficialDataError, match="missing \\(named by"):
        SymsoltOfficialDataModule(str(root), shapes=["cube"]).setup("test")


# ----------------------------------------------------------------------------- the commands
SO3_SMALL = ["+experiment=symsol_so3", "encoder.arch=resnet18", "data.num_workers=0", "data.image_size=32", "module.num_noisy=4",
             "data.batch_size=4", "trainer.max_steps=2", "trainer.val_check_interval=2", "eval.num_samples=2",
             "eval.num_steps=[3]", "trainer.enable_progress_bar=false", "eval.log_likelihood_steps=4"]  # fmt: skip
T_SMALL = ["+experiment=quickstart", "module.num_noisy=4", "data.batch_size=4", "trainer.max_steps=2",
           "trainer.val_check_interval=2", "eval.num_samples=2", "eval.before_num_samples=2", "eval.num_steps=[3]",
           "trainer.enable_progress_bar=false"]  # fmt: skip


@pytest.mark.parametrize("which", ["zip", "tfds", "symsolt"])
def test_fit_eval_predict_on_the_official_files(
    which: str,
    symsol_zip: Path,
    symsol_tfds: Path,
    symsolt_root: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if which == "symsolt":
        args = [*T_SMALL, "data=symsolt_official", f"data.root={symsolt_root}", "data.image_size=128"]
    else:
        args = [*SO3_SMALL, "data=symsol_official", f"data.root={symsol_zip if which == 'zip' else symsol_tfds}",
                "data.image_size=32", "data.shapes=[tet,cube,icosa,cone,cyl,tetX,cylO,sphereX]"]  # fmt: skip
        if which == "tfds":  # the default (on) is checked on the zip layout; one ODE pass is enough
            args.append("eval.log_likelihood=false")
    run = tmp_path / "fit"
    assert main(["fit", *args, f"hydra.run.dir={run}"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    rows = metrics["after"]["default"]["3"]["shapes"]
    expected = SHAPES if which == "symsolt" else ALL
    assert set(rows) == set(expected)
    ckpt = run / "checkpoints" / "last.ckpt"
    ev = tmp_path / "eval"
    # the data given whole (data=..., image_size its default 224 for SYMSOL-T): resized to the checkpoint's
    data = ["data=symsolt_official", f"data.root={symsolt_root}"] if which == "symsolt" else []
    capsys.readouterr()
    assert (
        main(
            [
                "eval",
                f"ckpt_path={ckpt}",
                "num_samples=2",
                "sampler.num_steps=3",
                *data,
                f"hydra.run.dir={ev}",
            ]
        )
        == 0
    )
    if which == "symsolt":
        line = "posediff eval: the checkpoint's encoder takes 128 px images; resizing the data's images to 128 px"
        assert line + " (data.image_size was 224)" in capsys.readouterr().out
    assert set(json.loads((ev / "metrics.json").read_text())["shapes"]) == set(expected)
    pr = tmp_path / "predict"
    assert main(["predict", f"ckpt_path={ckpt}", "index=1", "num_samples=4", f"hydra.run.dir={pr}"]) == 0
    assert (pr / "poses.json").is_file()
    assert torch.isfinite(torch.from_numpy(np.load(pr / "poses.npz")["samples"])).all()


def test_log_likelihood_units(symsol_zip: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A model whose score is zero everywhere leaves the ODE at rest: every ground truth gets the
    Haar prior's density, which in Implicit-PDF's units is exactly −ln π² (≈ −2.29)."""
    from posediff.evaluation import evaluate_data
    from posediff.models import load_checkpoint

    run = tmp_path / "fit"
    args = [*SO3_SMALL, "data=symsol_official", f"data.root={symsol_zip}", "data.image_size=32",
            "eval.before=false", "eval.log_likelihood=false", "diffusion.prior=haar"]  # fmt: skip
    assert main(["fit", *args, f"hydra.run.dir={run}"]) == 0
    module = load_checkpoint(run / "checkpoints" / "last.ckpt")
    dm = SymsolOfficialDataModule(str(symsol_zip), image_size=32, batch_size=5, group="so3")
    dm.setup("test")
    monkeypatch.setattr(type(module.diffusion), "to_score", lambda self, out, sigma: out * 0.0)
    res = evaluate_data(module, dm, num_samples=1, num_steps=2, log_likelihood=True, log_likelihood_steps=6)
    for row in res["shapes"].values():
        assert row["log_likelihood"] == pytest.approx(-np.log(np.pi**2), abs=1e-5)
        assert row["log_likelihood_ode_error"] == pytest.approx(0.0, abs=1e-6)
