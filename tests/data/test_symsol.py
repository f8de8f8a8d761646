"""SYMSOL / SYMSOL-T: meshes and symmetries, the headless renderer, shards, DataModule, CLI."""

import hashlib
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from posediff.data.symsol import (
    SCENE_DISTANCE,
    SHAPE_IDS,
    SymsolDataModule,
    SymsolRenderer,
    SymsolShards,
    authors_frame,
    equivalent_poses,
    make_mesh,
    render_dataset,
    sample_poses,
    symmetries,
)
from posediff.data.symsol.render import intrinsics
from posediff.symmetry import GOLDEN_RATIO, SHAPES

SIZE = 64


@pytest.fixture(scope="module")
def renderer() -> SymsolRenderer:
    r = SymsolRenderer(SIZE)
    yield r
    r.close()


# ----------------------------------------------------------------------------- shapes, symmetries
@pytest.mark.parametrize("shape", SHAPES)
def test_every_symmetry_maps_the_mesh_onto_itself(shape: str) -> None:
    V = torch.from_numpy(make_mesh(shape).vertices)
    G = symmetries(shape).discrete
    if len(G) > 60:  # cone / cylinder: every 7th grid rotation (and flip) is enough, and fast
        G = G[::7]
    moved = torch.einsum("sij,vj->svi", G, V)  # (S, V, 3)
    dist = (
        torch.cdist(moved, V[None].expand(len(G), -1, -1), compute_mode="donot_use_mm_for_euclid_dist")
        .min(-1)
        .values
    )
    assert dist.max() < 1e-9, f"{shape}: a symmetry moves a vertex off the vertex set by {dist.max():.2e}"


@pytest.mark.parametrize(
    ("shape", "count"), [("tet", 12), ("cube", 24), ("icosa", 60), ("cone", 360), ("cyl", 720)]
)
def test_symmetry_sets_are_closed_groups(shape: str, count: int) -> None:
    sym = symmetries(shape)
    G = sym.discrete
    assert len(sym) == count
    torch.testing.assert_close(G[0], torch.eye(3, dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    i, j = (
        torch.randint(len(G), (2, 3000), generator=g)
        if len(G) > 60
        else torch.cartesian_prod(*[torch.arange(len(G))] * 2).T
    )
    prod = (G[i] @ G[j]).reshape(-1, 1, 9)
    d = (
        torch.cdist(
            prod,
            G.reshape(1, -1, 9).expand(prod.shape[0], -1, -1),
            compute_mode="donot_use_mm_for_euclid_dist",
        )
        .min(-1)
        .values
    )
    assert d.max() < 1e-9, "product of two symmetries is not in the set"
    assert sym.continuous == (shape in ("cone", "cyl")) and sym.flip == (shape == "cyl")


@pytest.mark.parametrize("shape", SHAPES)
def test_meshes_are_sized_and_centred_like_the_authors(shape: str) -> None:
    m = make_mesh(shape)
    assert m.is_watertight
    np.testing.assert_allclose(m.center_mass, 0.0, atol=1e-9)
    radius = np.linalg.norm(m.vertices, axis=1).max()
    # Open3D's create_icosahedron(radius=1.4) scales the unnormalised vertices (0, ±1, ±φ): 2.663
    expected = {"tet": 3.5 / 1.3, "icosa": 1.4 * np.sqrt(1 + GOLDEN_RATIO**2), "cube": 3.5 * np.sqrt(3) / 2}
    if shape in expected:
        assert radius == pytest.approx(expected[shape], rel=1e-9)
    else:
        np.testing.assert_allclose(m.extents, [3.5, 3.5, 3.5], rtol=1e-9)


def test_equivalent_poses_keep_translation_and_start_with_the_pose() -> None:
    g = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(2, 4, generator=g, dtype=torch.float64), dim=-1)
    from posediff.lie import SO3

    R = SO3().exp(q[:, 1:] * 2)
    pose = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    pose[:, :3, :3], pose[:, :3, 3] = R, torch.tensor([0.1, -0.2, 9.0], dtype=torch.float64)
    eq = equivalent_poses("cube", pose)
    assert eq.shape == (2, 24, 4, 4)
    torch.testing.assert_close(eq[:, 0], pose)
    torch.testing.assert_close(eq[..., :3, 3], pose[:, None, :3, 3].expand(-1, 24, -1))
    torch.testing.assert_close(eq[..., :3, :3], R[:, None] @ symmetries("cube").discrete)
    assert equivalent_poses("cyl", R).shape == (2, 720, 3, 3)
    with pytest.raises(ValueError, match="available: tet, cube"):
        symmetries("sphere")


# ----------------------------------------------------------------------------- rendering
@pytest.mark.parametrize("variant", ["uniform", "edge", "centered"])
def test_projected_centre_is_the_mask_centroid_and_nothing_is_clipped(
    renderer: SymsolRenderer, variant: str
) -> None:
    poses = sample_poses("symsolt", variant, "test", 4, seed=1)
    for sid, R, t in zip(poses.shape_id, poses.R, poses.t, strict=True):
        out = renderer.render(int(sid), R, t)
        assert out.mask.any(), "empty mask"
        border = np.concatenate([out.mask[0], out.mask[-1], out.mask[:, 0], out.mask[:, -1]])
        assert not border.any(), f"{SHAPES[sid]} at t={t} touches the image border"
        uv = out.K @ t
        uv = uv[:2] / uv[2]
        ys, xs = np.nonzero(out.mask)
        centroid = np.array([xs.mean(), ys.mean()]) + 0.5  # pixel centres
        # perspective moves a silhouette's centroid off the projected centre by a few % of its size;
        # a flipped axis or a wrong K would be off by the whole offset (≥ 10 px here for |t| ≥ 0.5)
        tol = 1.0 + 0.12 * np.sqrt(out.mask.sum())
        assert np.abs(centroid - uv).max() < tol, (
            f"{SHAPES[sid]}: centroid {centroid} vs K·t {uv} (tol {tol:.1f})"
        )
        assert out.depth[out.mask].min() > 0 and out.depth[~out.mask].max() == 0
        near = out.mask.copy()  # anti-aliased edges and thin tips may be grey just outside the mask
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                near |= np.roll(out.mask, (dy, dx), axis=(0, 1))
        assert out.rgb[~near].max() == 0, "background must be black"


def test_y_axis_points_down(renderer: SymsolRenderer) -> None:
    out = renderer.render("cube", np.eye(3), np.array([0.0, 1.0, SCENE_DISTANCE]))
    ys, _ = np.nonzero(out.mask)
    assert ys.mean() > SIZE / 2 + 2, "positive camera y must be lower in the image (OpenCV frame)"


@pytest.mark.parametrize("shape", SHAPES)
def test_symmetric_poses_render_alike(renderer: SymsolRenderer, shape: str) -> None:
    poses = sample_poses("symsolt", "uniform", "train", 1, seed=2, shapes=[shape])
    R, t = poses.R[0], poses.t[0]
    base = renderer.render(shape, R, t)
    G = symmetries(shape).discrete.numpy()
    picks = G[[1, len(G) // 2, len(G) - 1]]
    if shape in ("cone", "cyl"):  # off the 1° grid too: the continuous symmetry
        a = np.deg2rad(37.3)
        picks = np.concatenate([picks, [[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]]])

    def diff(other) -> float:  # noqa: ANN001 — mean |Δ| grey level over the object's pixels
        region = base.mask | other.mask
        return float(np.abs(base.rgb.astype(int) - other.rgb.astype(int))[region].mean())

    for S in picks:
        other = renderer.render(shape, R @ S, t)
        assert diff(other) < 2.0, (
            f"{shape}: a symmetric pose renders differently (mean |Δ| {diff(other):.2f})"
        )
        assert (base.mask != other.mask).sum() <= 0.03 * base.mask.sum()
    different = renderer.render(shape, R @ _rx(0.6), t)
    assert diff(different) > 8.0, f"the test cannot tell poses apart ({diff(different):.2f})"


def _rx(a: float) -> np.ndarray:
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def test_intrinsics_match_the_authors() -> None:
    K = intrinsics(224)
    assert K[0, 0] == pytest.approx(193.990, abs=1e-3) and K[0, 2] == 112
    assert pytest.approx(9.09327, abs=1e-5) == SCENE_DISTANCE


def test_renderer_pickles_without_its_context(renderer: SymsolRenderer) -> None:
    import pickle

    first = renderer.render("tet", np.eye(3), np.array([0, 0, SCENE_DISTANCE]))
    clone = pickle.loads(pickle.dumps(renderer))
    again = clone.render("tet", np.eye(3), np.array([0, 0, SCENE_DISTANCE]))
    assert again.mask.any()
    np.testing.assert_array_equal(again.rgb, first.rgb)


def _authors_translation(poses: object) -> np.ndarray:
    """The scene translations of the authors' model origins (what the variants draw)."""
    out = []
    for sid, R, t in zip(poses.shape_id, poses.R, poses.t, strict=True):  # type: ignore[attr-defined]
        C, o = authors_frame(int(sid))
        out.append(t - R @ (C.T @ o) - [0, 0, SCENE_DISTANCE])
    return np.asarray(out)


# ----------------------------------------------------------------------------- poses
def test_pose_sampling_is_deterministic_and_splits_differ() -> None:
    a = sample_poses("symsolt", "uniform", "train", 50, seed=0)
    b = sample_poses("symsolt", "uniform", "train", 50, seed=0)
    c = sample_poses("symsolt", "uniform", "test", 50, seed=0)
    np.testing.assert_array_equal(a.R, b.R)
    assert not np.allclose(a.R[:5], c.R[:5])
    assert np.bincount(a.shape_id).tolist() == [50] * 5
    assert len(set(a.shape_id[:10].tolist())) > 1, "shapes must be interleaved"
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", a.R, a.R), np.broadcast_to(np.eye(3), a.R.shape), atol=1e-12
    )
    scene = _authors_translation(a)
    assert np.abs(scene).max() <= 1 and np.abs(scene).max() > 0.9
    edge = _authors_translation(sample_poses("symsolt", "edge", "train", 20, seed=0))
    np.testing.assert_allclose(np.abs(edge), 1.0)
    cone = a.shape_id == SHAPE_IDS["cone"]  # posediff's pose is the centre of mass, h/4 − h/362 up the axis
    lever = np.linalg.norm(a.t[cone] - [0, 0, SCENE_DISTANCE] - scene[cone], axis=1)
    np.testing.assert_allclose(lever, 3.5 / 4 - 3.5 / 362, rtol=1e-9)
    np.testing.assert_allclose(
        sample_poses("symsol", None, "train", 5, seed=0).t - [0, 0, SCENE_DISTANCE], 0.0
    )
    with pytest.raises(ValueError, match="available: uniform, edge, centered"):
        sample_poses("symsolt", "corner", "train", 5, seed=0)
    with pytest.raises(ValueError, match="no shapes given"):
        sample_poses("symsolt", "uniform", "train", 5, seed=0, shapes=[])
    with pytest.raises(ValueError, match="at least 1"):
        sample_poses("symsolt", "uniform", "train", 0, seed=0)


# ----------------------------------------------------------------------------- shards
def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.glob("*.npz"))}


def test_shards_are_byte_identical_resumable_and_atomic(tmp_path: Path) -> None:
    kw = dict(
        dataset="symsolt",
        variant="edge",
        split="train",
        n_per_shape=6,
        image_size=32,
        shard_size=8,
        progress=False,
    )
    first = render_dataset(tmp_path / "a", **kw)
    assert first.images == first.rendered == 30
    render_dataset(tmp_path / "b", **kw)
    split_a, split_b = tmp_path / "a" / "train", tmp_path / "b" / "train"
    assert _digests(split_a) == _digests(split_b) and len(_digests(split_a)) == 1 + 4
    # an interrupted run: two shards missing, meta not complete, a stray temporary file
    (split_b / "shard-00001.npz").unlink()
    (split_b / "shard-00003.npz").unlink()
    meta = json.loads((split_b / "meta.json").read_text())
    meta["complete"] = False
    (split_b / "meta.json").write_text(json.dumps(meta))
    (split_b / ".shard-00001.npz.x.tmp").write_bytes(b"half")
    with pytest.raises(RuntimeError, match="unfinished .* finish it with: posediff data render"):
        SymsolShards(tmp_path / "b", split="train")
    again = render_dataset(tmp_path / "b", **kw)
    assert again.rendered == 8 + 6
    assert _digests(split_a) == _digests(split_b)
    # another dataset in the same folder is refused
    with pytest.raises(ValueError, match="already holds another dataset"):
        render_dataset(tmp_path / "b", **{**kw, "seed": 1})
    # reading back
    ds = SymsolShards(tmp_path / "a", split="train")
    samples = list(ds.iter_samples())
    assert len(samples) == len(ds) == 30
    assert sorted(s["index"] for s in samples) == list(range(30))
    s = samples[3]
    assert s["rgb"].shape == (32, 32, 3) and s["mask"].any() and s["depth"][s["mask"]].min() > 5
    np.testing.assert_array_equal(s["mask"], s["depth"] > 0)


def test_missing_and_corrupt_data_fail_with_one_line(tmp_path: Path) -> None:
    with pytest.raises(
        FileNotFoundError, match=r"no rendered symsolt test split at .*make it with: posediff data render"
    ):
        SymsolShards(tmp_path / "nothing", split="test")
    render_dataset(tmp_path, split="test", n_per_shape=2, image_size=16, shard_size=4, progress=False)
    shard = tmp_path / "test" / "shard-00001.npz"
    shard.write_bytes(shard.read_bytes()[:100])
    with pytest.raises(RuntimeError, match="corrupt shard .*shard-00001.npz"):  # found on opening the split
        SymsolShards(tmp_path, split="test")
    with pytest.raises(ValueError, match="data.root is not set"):
        SymsolDataModule("symsolt", root=None)
    with pytest.raises(ValueError, match="3-D rotation group"):
        SymsolDataModule("symsolt", mode="render", group="se2")


# ----------------------------------------------------------------------------- DataModule
def _check_batch(batch: dict, n: int, size: int) -> None:
    assert batch["image"].shape == (n, 3, size, size) and batch["image"].dtype == torch.float32
    assert 0 <= batch["image"].min() and batch["image"].max() <= 1 and batch["image"].max() > 0.2
    assert batch["camera_pose"].shape == (n, 4, 4) and batch["K"].shape == (n, 3, 3)
    torch.testing.assert_close(batch["camera_pose"][:, :3, :3], batch["rotation"])
    torch.testing.assert_close(
        batch["camera_pose"][:, :3, 3] - torch.tensor([0, 0, SCENE_DISTANCE]), batch["translation"]
    )
    if batch["pose"].shape[-1] == 4:
        torch.testing.assert_close(batch["pose"][:, :3, :3], batch["rotation"])
        torch.testing.assert_close(batch["pose"][:, :3, 3], batch["translation"])
    else:
        torch.testing.assert_close(batch["pose"], batch["rotation"])
    assert batch["shape"].dtype == torch.int64 and set(batch["shape"].tolist()) <= set(SHAPE_IDS.values())


def test_datamodule_streams_shards_and_renders_on_the_fly(tmp_path: Path) -> None:
    for split, n in (("train", 8), ("test", 2)):
        render_dataset(tmp_path, split=split, n_per_shape=n, image_size=32, shard_size=16, progress=False)
    dm = SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=32, batch_size=8)
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    assert len(batches) == 4  # 38 training samples: the last 2 (5%) are held out for validation
    _check_batch(batches[0], 8, 32)
    seen = torch.cat([b["index"] for b in batches])
    assert len(set(seen.tolist())) == 32 and int(seen.max()) < 38
    assert not torch.equal(seen, torch.arange(32)), "training order must be shuffled"
    assert torch.cat([b["index"] for b in dm.val_dataloader()]).tolist() == [38, 39]
    test = torch.cat([b["index"] for b in dm.test_dataloader()])
    assert test.tolist() == list(range(10))
    sub = SymsolDataModule(
        "symsolt", "uniform", root=str(tmp_path), image_size=32, shapes=["cube"], batch_size=2
    )
    sub.setup("fit")
    ids = torch.cat([b["shape"] for b in sub.train_dataloader()])  # 7 cubes (1 held out), batches of 2
    assert len(ids) == 6 and set(ids.tolist()) == {SHAPE_IDS["cube"]}, "a subset of the rendered shapes"
    assert {int(b["shape"][0]) for b in sub.val_dataloader()} == {SHAPE_IDS["cube"]}
    limited = SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=32, n_per_shape_test=1)
    limited.setup("test")
    assert sorted(torch.cat([b["shape"] for b in limited.test_dataloader()]).tolist()) == list(range(5))
    with pytest.raises(ValueError, match=r"not \['nope'\]"):
        SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=32, shapes=["nope"]).setup(
            "fit"
        )
    with pytest.raises(ValueError, match="rendered at 32 px"):
        SymsolDataModule("symsolt", "uniform", root=str(tmp_path), image_size=64).setup("fit")

    live = SymsolDataModule(
        "symsolt", "edge", mode="render", image_size=32, n_per_shape_train=2, batch_size=4, with_depth=True
    )
    live.setup("fit")
    batch = next(iter(live.train_dataloader()))
    _check_batch(batch, 4, 32)
    torch.testing.assert_close(batch["mask"], batch["depth"] > 0)
    cone = batch["shape"] == SHAPE_IDS["cone"]
    torch.testing.assert_close(batch["translation"][~cone].abs(), torch.ones(int((~cone).sum()), 3))


def test_gl_traps_are_handled_in_the_module(tmp_path: Path) -> None:
    """In a fresh process: make a GL context in the parent (the BOP renderer: SYMSOL renders without
    GL since scene 2), then fork DataLoader workers that render (the hang), then import triton /
    torch._dynamo after a GL context exists (the segfault)."""
    script = textwrap.dedent(
        """
        import numpy as np, torch, trimesh
        from posediff.data.bop.render import BopRenderer
        from posediff.data.symsol import SymsolDataModule
        gl = BopRenderer(32, 32)
        gl.add_model(1, trimesh.creation.box(extents=(50.0, 50.0, 50.0)))
        K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
        assert gl.render([(1, np.eye(3), np.array([0.0, 0.0, 300.0]))], K).rgb.any()
        dm = SymsolDataModule("symsolt", mode="render", image_size=32, n_per_shape_train=2, batch_size=5, num_workers=2)
        dm.setup("fit")
        n = sum(len(b["image"]) for b in dm.train_dataloader())
        import torch._dynamo  # noqa: F401
        try:
            import triton  # noqa: F401
        except ImportError:
            pass
        print("ok", n)
        """
    )
    env = {
        k: v for k, v in os.environ.items() if k not in ("LP_NUM_THREADS", "PYOPENGL_PLATFORM")
    }  # the module's job
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=240, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ok 10" in proc.stdout


# ----------------------------------------------------------------------------- CLI
def test_cli_render_and_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from posediff.cli import main

    out = tmp_path / "ds"
    args = [
        "data",
        "render",
        "dataset=symsol",
        "split=test",
        "n_per_shape=2",
        "image_size=16",
        "progress=false",
        f"out={out}",
    ]
    assert main(args) == 0
    assert "10 images in" in capsys.readouterr().out
    assert json.loads((out / "test" / "meta.json").read_text())["complete"]
    assert main([*args[:-1], f"out={out}", "seed=5"]) == 2
    assert "already holds another dataset" in capsys.readouterr().err
    assert main(["data", "render", "dataset=symsol", "variant=edge", f"out={out}"]) == 2
    assert main(["data", "render", "preset=huge"]) == 2
    assert "available: cpu, paper" in capsys.readouterr().err
    assert main(["data", "explode"]) == 2


# ----------------------------------------------------------------------------- configs
CONF = Path(__file__).resolve().parents[2] / "conf"


def _compose(name: str, overrides: list[str]):  # noqa: ANN202
    from hydra import compose, initialize_config_dir

    from posediff.config import register_resolvers

    register_resolvers()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


@pytest.mark.parametrize(
    ("preset", "split", "size", "n"),
    [("cpu", "train", 64, 2000), ("paper", "train", 224, 45000), ("paper", "test", 224, 5000)],
)
def test_render_presets(preset: str, split: str, size: int, n: int) -> None:
    cfg = _compose("render", [f"preset={preset}", f"split={split}"])
    assert (cfg.image_size, cfg.n_per_shape) == (size, n)


# posediff's own renders (the official files' configs are tests/evaluation/test_official_data.py's)
@pytest.mark.parametrize(
    "name", sorted(p.stem for p in (CONF / "data").glob("symsol*.yaml") if not p.stem.endswith("_official"))
)
def test_every_symsol_data_config_builds(name: str, tmp_path: Path) -> None:
    from hydra.utils import instantiate

    cfg = _compose(
        "fit",
        [
            f"data={name}",
            "data.mode=render",
            "data.n_per_shape_train=1",
            "data.image_size=32",
            "data.batch_size=5",
        ],
    )
    dm = instantiate(cfg.data)
    assert isinstance(dm, SymsolDataModule) and dm.variant == cfg.data.variant
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    _check_batch(batch, 5, 32)
    assert batch["pose"].shape[-1] == dm.group.matrix_dim  # fit.yaml's group: so3 → R alone
    # shards mode without the folder: one line with the command that makes it
    cfg = _compose("fit", [f"data={name}", f"data.root={tmp_path / 'none'}"])
    with pytest.raises(
        FileNotFoundError,
        match=f"make it with: posediff data render dataset={cfg.data.dataset} variant={cfg.data.variant}",
    ):
        instantiate(cfg.data).setup("fit")
