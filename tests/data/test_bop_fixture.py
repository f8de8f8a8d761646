"""The BOP mesh renderer and the BOP-format fixture: layout, JSON, depth, masks, boxes, symmetries."""

import json
import math
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from posediff.data.bop.fixture import (
    DEPTH_SCALE,
    MIN_VISIB_FRACT,
    OBJ_IDS,
    SPLITS,
    FixtureExistsError,
    camera,
    diameter,
    make_bop_fixture,
    make_model,
    rot_z,
)
from posediff.data.bop.render import BopRenderer

W, H = 240, 180
SIZES = {
    "width": W,
    "height": H,
    "pbr_scenes": 1,
    "pbr_images": 2,
    "pbr_instances": 5,
    "train_views": 2,
    "test_scenes": 2,
    "test_images": 2,
    "test_instances": 6,
}
RGB_EXT = {"train_pbr": ".jpg", "train_primesense": ".png", "test_primesense": ".png"}
GT_KEYS = {"cam_R_m2c", "cam_t_m2c", "obj_id"}
INFO_KEYS = {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract"}


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    out = tmp_path_factory.mktemp("bop") / "fixture"
    summary = make_bop_fixture(out, seed=0, **SIZES)
    return out, summary


@pytest.fixture(scope="module")
def root(made) -> Path:  # noqa: ANN001
    return made[0]


@pytest.fixture(scope="module")
def models(root: Path) -> dict[int, trimesh.Trimesh]:
    return {i: trimesh.load(root / "models" / f"obj_{i:06d}.ply", process=False) for i in OBJ_IDS}


@pytest.fixture(scope="module")
def renderer(models: dict[int, trimesh.Trimesh]) -> BopRenderer:
    r = BopRenderer(W, H)
    for i, mesh in models.items():
        r.add_model(i, mesh)
    yield r
    r.close()


def _json(path: Path):  # noqa: ANN202
    return json.loads(path.read_text())


def _scenes(root: Path):  # noqa: ANN202
    """(split, scene dir, scene_gt, scene_camera, scene_gt_info) of every scene."""
    for split in SPLITS:
        for scene in sorted((root / split).iterdir()):
            yield (
                split,
                scene,
                _json(scene / "scene_gt.json"),
                _json(scene / "scene_camera.json"),
                _json(scene / "scene_gt_info.json"),
            )


def _read(path: Path) -> np.ndarray:
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert im is not None, f"cannot read {path}"
    return im


def _pose(gt: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.array(gt["cam_R_m2c"]).reshape(3, 3), np.array(gt["cam_t_m2c"])


def _sym_matrices(info: dict) -> list[np.ndarray]:
    return [np.array(s).reshape(4, 4) for s in info.get("symmetries_discrete", [])]


# ---------------------------------------------------------------------------------------- layout
def test_layout_and_json_keys(made) -> None:  # noqa: ANN001
    root, summary = made
    top = {p.name for p in root.iterdir()}
    assert top == {
        "camera_primesense.json",
        "models",
        "models_eval",
        *SPLITS,
        "test_targets_bop19.json",
        ".posediff-output",
    }
    assert not root.with_name(root.name + ".partial").exists()
    cam = _json(root / "camera_primesense.json")
    assert set(cam) == {"cx", "cy", "depth_scale", "fx", "fy", "height", "width"}
    assert (cam["width"], cam["height"], cam["depth_scale"]) == (W, H, DEPTH_SCALE)
    assert cam["fx"] == pytest.approx(1075.65 * W / 720) and cam["cy"] == pytest.approx(257.73 * H / 540)
    for folder in ("models", "models_eval"):
        names = {p.name for p in (root / folder).iterdir()}
        assert names == {"models_info.json", *(f"obj_{i:06d}.ply" for i in OBJ_IDS)}
    for name in names:
        assert (root / "models" / name).read_bytes() == (root / "models_eval" / name).read_bytes()
    info = _json(root / "models" / "models_info.json")
    assert list(info) == ["1", "2", "3"]
    base = {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"}
    assert set(info["1"]) == base | {"symmetries_continuous", "symmetries_discrete"}
    assert set(info["2"]) == base | {"symmetries_discrete"}
    assert set(info["3"]) == base
    assert info["1"]["symmetries_continuous"] == [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    assert all(len(s) == 16 for s in info["2"]["symmetries_discrete"])

    counts = {split: [0, 0, 0] for split in SPLITS}
    for split, scene, gt, cams, gt_info in _scenes(root):
        counts[split][0] += 1
        assert list(gt) == list(cams) == list(gt_info) == [str(k) for k in range(len(gt))]
        for im_id, entries in gt.items():
            counts[split][1] += 1
            counts[split][2] += len(entries)
            name = f"{int(im_id):06d}"
            assert (scene / "rgb" / f"{name}{RGB_EXT[split]}").is_file()
            assert _read(scene / "depth" / f"{name}.png").dtype == np.uint16
            assert len(gt_info[im_id]) == len(entries)
            assert set(cams[im_id]) >= {"cam_K", "depth_scale"} and len(cams[im_id]["cam_K"]) == 9
            assert cams[im_id]["depth_scale"] == DEPTH_SCALE
            for k, (e, inf) in enumerate(zip(entries, gt_info[im_id], strict=True)):
                assert set(e) == GT_KEYS and set(inf) == INFO_KEYS
                assert len(e["cam_R_m2c"]) == 9 and len(e["cam_t_m2c"]) == 3 and e["obj_id"] in OBJ_IDS
                for sub in ("mask", "mask_visib"):
                    m = _read(scene / sub / f"{name}_{k:06d}.png")
                    assert m.dtype == np.uint8 and m.shape == (H, W) and set(np.unique(m)) <= {0, 255}
            ids = [e["obj_id"] for e in entries]
            assert ids == sorted(ids), "instances are listed by ascending obj_id"
    # scene ids as T-LESS: train_primesense = obj id, test from 1, pbr from 0
    assert sorted(p.name for p in (root / "train_primesense").iterdir()) == [f"{i:06d}" for i in OBJ_IDS]
    assert sorted(p.name for p in (root / "test_primesense").iterdir()) == ["000001", "000002"]
    assert sorted(p.name for p in (root / "train_pbr").iterdir()) == ["000000"]
    for split, (scenes, images, instances) in counts.items():
        c = summary.splits[split]
        assert (c.scenes, c.images, c.instances) == (scenes, images, instances)
    assert counts["train_pbr"] == [1, 2, 10]
    assert counts["train_primesense"] == [3, 6, 6]
    assert counts["test_primesense"] == [2, 4, 24]
    assert str(root) in summary.line() and "test_primesense 2 scenes / 4 images" in summary.line()
    # several instances of one object in the cluttered splits
    for split in ("train_pbr", "test_primesense"):
        for _, _, gt, _, _ in (s for s in _scenes(root) if s[0] == split):
            ids = [e["obj_id"] for e in gt["0"]]
            assert len(set(ids)) < len(ids)


def test_models_match_their_info(root: Path, models: dict[int, trimesh.Trimesh]) -> None:
    info = _json(root / "models" / "models_info.json")
    for i, mesh in models.items():
        inf = info[str(i)]
        V = mesh.vertices
        assert len(mesh.vertex_normals) == len(V)
        lo, size = V.min(0), V.max(0) - V.min(0)
        assert [inf["min_x"], inf["min_y"], inf["min_z"]] == pytest.approx(lo, abs=1e-9)
        assert [inf["size_x"], inf["size_y"], inf["size_z"]] == pytest.approx(size, abs=1e-9)
        assert np.allclose(V.min(0) + V.max(0), 0.0, atol=1e-5), "origin at the bounding-box centre"
        brute = np.linalg.norm(V[:, None] - V[None], axis=-1).max()
        assert inf["diameter"] == pytest.approx(brute, abs=1e-9) == diameter(V)
        assert 40.0 <= inf["diameter"] <= 100.0
        assert np.abs(make_model(i).vertices - V).max() < 1e-12, "the PLY holds the rendered model"


# ------------------------------------------------------------------------------------------ depth
def test_depth_png_reproduces_the_rendered_depth(root: Path, renderer: BopRenderer) -> None:
    checked = 0
    for split, scene, gt, cams, _ in _scenes(root):
        for im_id in list(gt)[:1]:
            name = f"{int(im_id):06d}"
            depth_mm = _read(scene / "depth" / f"{name}.png").astype(np.float64) * cams[im_id]["depth_scale"]
            K = np.array(cams[im_id]["cam_K"]).reshape(3, 3)
            for k, e in enumerate(gt[im_id]):
                own = renderer.render_depth(e["obj_id"], *_pose(e), K)
                visib = _read(scene / "mask_visib" / f"{name}_{k:06d}.png") > 0
                assert ((own > 0) == (_read(scene / "mask" / f"{name}_{k:06d}.png") > 0)).all()
                err = np.abs(depth_mm[visib] - own[visib])
                assert err.max() <= DEPTH_SCALE / 2 + 1e-3, f"{split}/{scene.name}/{name} gt {k}: {err.max()}"
                checked += visib.sum()
            if split == "train_primesense":  # the object alone: the depth image is all of it
                assert ((depth_mm > 0) == (own > 0)).all()
    assert checked > 1000


def test_renderer_scene_depth_agrees_with_instances(renderer: BopRenderer, root: Path) -> None:
    _, scene, gt, cams, _ = next(s for s in _scenes(root) if s[0] == "test_primesense")
    K = np.array(cams["0"]["cam_K"]).reshape(3, 3)
    inst = [(e["obj_id"], *_pose(e)) for e in gt["0"]]
    out = renderer.render(inst, K)
    assert out.rgb.shape == (H, W, 3) and out.rgb.dtype == np.uint8
    assert out.depth.shape == (H, W) and out.depth.dtype == np.float32
    assert len(out.depth_per_instance) == len(inst)
    stacked = np.stack([np.where(d > 0, d, np.inf) for d in out.depth_per_instance]).min(0)
    stacked[np.isinf(stacked)] = 0
    assert np.abs(stacked - out.depth).max() < 1e-3, "scene depth = nearest of the instances' depths"
    for k, (obj_id, R, t) in enumerate(inst):
        assert np.array_equal(out.depth_per_instance[k], renderer.render_depth(obj_id, R, t, K))


# ------------------------------------------------------------------------------------ masks, boxes
def _bbox(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def test_masks_boxes_and_counts(root: Path, models: dict[int, trimesh.Trimesh]) -> None:
    fracts = {split: [] for split in SPLITS}
    for split, scene, gt, cams, gt_info in _scenes(root):
        for im_id, entries in gt.items():
            name = f"{int(im_id):06d}"
            K = np.array(cams[im_id]["cam_K"]).reshape(3, 3)
            depth = _read(scene / "depth" / f"{name}.png")
            for k, (e, inf) in enumerate(zip(entries, gt_info[im_id], strict=True)):
                mask = _read(scene / "mask" / f"{name}_{k:06d}.png") > 0
                visib = _read(scene / "mask_visib" / f"{name}_{k:06d}.png") > 0
                assert not (visib & ~mask).any(), "mask_visib must lie inside mask"
                assert inf["px_count_all"] == mask.sum() > 0
                assert inf["px_count_visib"] == visib.sum()
                assert inf["px_count_valid"] == (mask & (depth > 0)).sum()
                assert 0.0 <= inf["visib_fract"] <= 1.0
                assert inf["visib_fract"] == pytest.approx(visib.sum() / mask.sum())
                assert inf["bbox_obj"] == _bbox(mask) and inf["bbox_visib"] == _bbox(visib)
                # the model's vertices project inside bbox_obj (give or take the 1.5 px a sharp
                # corner can poke out between pixel centres), and every pixel of it is inside theirs;
                # pixel (col, row) is sampled at image coordinates (col + 1/2, row + 1/2) (render.py)
                R, t = _pose(e)
                p = models[e["obj_id"]].vertices @ R.T + t
                uv = p[:, :2] / p[:, 2:] * np.diag(K)[:2] + K[:2, 2]
                x, y, w, h = inf["bbox_obj"]
                lo, hi = np.array([x, y]) + 0.5, np.array([x + w, y + h]) - 0.5
                where = (split, scene.name, im_id, k)
                assert (uv.min(0) >= lo - 1.5).all() and (uv.max(0) <= hi + 1.5).all(), where
                assert (uv.min(0) <= lo).all() and (uv.max(0) >= hi).all(), where
                assert 480 <= p[:, 2].min() and p[:, 2].max() <= 900, "objects 500–800 mm away"
                fracts[split].append(inf["visib_fract"])
    assert min(fracts["train_primesense"]) == 1.0
    test = np.array(fracts["test_primesense"])
    assert (test < 0.9).sum() >= 3, "test scenes must have occluded instances"
    assert test.min() < MIN_VISIB_FRACT, "and at least one that is hardly visible"


def test_targets_follow_the_bop19_rule(root: Path, made) -> None:  # noqa: ANN001
    expected = []
    for split, scene, gt, _, gt_info in _scenes(root):
        if split != "test_primesense":
            continue
        for im_id, entries in gt.items():
            counted: dict[int, int] = {}
            for e, inf in zip(entries, gt_info[im_id], strict=True):
                if inf["visib_fract"] >= MIN_VISIB_FRACT:
                    counted[e["obj_id"]] = counted.get(e["obj_id"], 0) + 1
            for obj_id in sorted(counted):
                expected.append(
                    {
                        "im_id": int(im_id),
                        "inst_count": counted[obj_id],
                        "obj_id": obj_id,
                        "scene_id": int(scene.name),
                    }
                )
    targets = _json(root / "test_targets_bop19.json")
    assert targets == expected
    assert made[1].targets == len(targets)
    assert (
        made[1].target_instances
        == sum(t["inst_count"] for t in targets)
        < made[1].splits["test_primesense"].instances
    )


# ------------------------------------------------------------------------------------- symmetries
def test_symmetries_map_the_mesh_onto_itself(root: Path, models: dict[int, trimesh.Trimesh]) -> None:
    info = _json(root / "models" / "models_info.json")
    for i, mesh in models.items():
        V = mesh.vertices
        syms = _sym_matrices(info[str(i)])
        for c in info[str(i)].get("symmetries_continuous", []):
            axis = np.array(c["axis"], dtype=float)
            for angle in (2 * math.pi / 48, 2 * math.pi * 7 / 48, math.pi):  # the cylinder has 48 sides
                S = np.eye(4)
                S[:3, :3] = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
                S[:3, 3] = c["offset"]
                syms.append(S)
        for S in syms:
            moved = V @ S[:3, :3].T + S[:3, 3]
            d = np.linalg.norm(moved[:, None] - V[None], axis=-1).min(1)
            assert d.max() < 1e-4, f"obj {i}: a symmetry moves a vertex {d.max():.2e} mm off the mesh"
    # the asymmetric part is not mapped onto itself by a half turn about any axis
    V = models[3].vertices
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        assert np.linalg.norm((V @ R.T)[:, None] - V[None], axis=-1).min(1).max() > 1.0


def test_render_depth_is_the_same_at_a_symmetric_pose(root: Path, renderer: BopRenderer) -> None:
    info = _json(root / "models" / "models_info.json")
    K = np.array(_json(root / "test_primesense" / "000001" / "scene_camera.json")["0"]["cam_K"]).reshape(3, 3)
    rng = np.random.default_rng(3)
    for obj_id in (1, 2):
        syms = _sym_matrices(info[str(obj_id)])
        if obj_id == 1:
            S = np.eye(4)
            S[:3, :3] = trimesh.transformations.rotation_matrix(0.7, [0, 0, 1])[:3, :3]  # any angle
            syms.append(S)
        for _ in range(2):
            q = rng.standard_normal(4)
            R = trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3]
            t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(550, 700)])
            ref = renderer.render_depth(obj_id, R, t, K)
            for S in syms:
                other = renderer.render_depth(obj_id, R @ S[:3, :3], t + R @ S[:3, 3], K)
                both = (ref > 0) & (other > 0)
                differ = (ref > 0) != (other > 0)
                assert differ.sum() <= 0.01 * (ref > 0).sum() + 4, f"obj {obj_id}: silhouettes differ"
                err = np.abs(ref[both] - other[both])
                if S is syms[-1] and obj_id == 1:  # the 48-gon turned by any angle: ~0.05 mm radially
                    assert np.median(err) < 0.05 and np.quantile(err, 0.95) < 0.5
                else:
                    assert np.quantile(err, 0.99) < 0.01, f"obj {obj_id}: depth differs at a symmetric pose"
    # and the asymmetric part is not: a half turn changes its depth
    R = trimesh.transformations.euler_matrix(0.6, 0.4, 0.2)[:3, :3]
    t = np.array([0.0, 0.0, 600.0])
    ref = renderer.render_depth(3, R, t, K)
    flipped = renderer.render_depth(3, R @ np.diag([-1.0, -1.0, 1.0]), t, K)
    assert (np.abs(ref - flipped) > 1.0).sum() > 100


# ---------------------------------------------------------------------------------------- renderer
def test_renderer_intrinsics_background_and_pickling() -> None:
    r = BopRenderer(160, 100)
    r.add_model(7, trimesh.creation.box(extents=(6.0, 6.0, 6.0)), color=(1.0, 0.0, 0.0))
    K = np.array([[520.0, 0.0, 61.3], [0.0, 430.0, 57.8], [0.0, 0.0, 1.0]])  # fx != fy, off-centre
    try:
        for t in ([0.0, 0.0, 500.0], [45.0, -30.0, 520.0]):
            depth = r.render_depth(7, np.eye(3), t, K)
            ys, xs = np.nonzero(depth > 0)
            u = K[0, 0] * t[0] / t[2] + K[0, 2]
            v = K[1, 1] * t[1] / t[2] + K[1, 2]
            # pixel (col, row) is centred at image coordinates (col + 1/2, row + 1/2) (render.py)
            assert abs(xs.mean() + 0.5 - u) < 0.6 and abs(ys.mean() + 0.5 - v) < 0.6, "p lands at K (R p + t)"
            assert depth[depth > 0].min() == pytest.approx(t[2] - 3.0, abs=0.01)
        bg = np.full((100, 160, 3), (10, 200, 30), np.uint8)
        out = r.render([(7, np.eye(3), [0.0, 0.0, 500.0])], K, background=bg)
        empty = out.depth == 0
        assert (out.rgb[empty] == bg[empty]).all(), "the background shows where nothing was drawn"
        inner = cv2.erode((~empty).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert (out.rgb[inner][:, 0] > out.rgb[inner][:, 1]).all(), "the model's own colour"
        assert len(out.depth_per_instance) == 1 and np.array_equal(out.depth_per_instance[0], out.depth)
        clone = pickle.loads(pickle.dumps(r))  # without the GL context
        assert clone._gl is None and clone.obj_ids == [7]
        again = clone.render_depth(7, np.eye(3), [0.0, 0.0, 500.0], K)
        assert np.array_equal(again, r.render_depth(7, np.eye(3), [0.0, 0.0, 500.0], K))
        clone.close()
        r.close()
        r.close()  # twice is harmless, and rendering again makes a new context
        assert np.array_equal(r.render_depth(7, np.eye(3), [0.0, 0.0, 500.0], K), again)
        with pytest.raises(KeyError, match="unknown obj_id 8"):
            r.render_depth(8, np.eye(3), [0.0, 0.0, 500.0], K)
    finally:
        r.close()


def _inside_polygon(px: np.ndarray, py: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether points lie inside a convex polygon (counter-clockwise or clockwise), and their distance
    to its nearest edge (to leave out points on the boundary)."""
    inside_pos = np.ones(px.shape, bool)
    inside_neg = np.ones(px.shape, bool)
    dist = np.full(px.shape, np.inf)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        e = b - a
        cross = e[0] * (py - a[1]) - e[1] * (px - a[0])
        inside_pos &= cross > 0
        inside_neg &= cross < 0
        dist = np.minimum(dist, np.abs(cross) / np.linalg.norm(e))
    return inside_pos | inside_neg, dist


def test_renderer_pixel_masks_equal_a_hand_projection() -> None:
    """The BOP toolkit's camera convention (render.py): pixel (col, row) is covered exactly when the ray
    through image coordinates (col + 1/2, row + 1/2) of K hits the model. A thin plate facing the camera,
    turned about the optical axis, projects to a quadrilateral: its corners K (R p + t) / z."""
    W, H = 160, 120
    K = np.array([[520.0, 0.0, 71.3], [0.0, 430.0, 57.8], [0.0, 0.0, 1.0]])  # fx != fy, off-centre
    r = BopRenderer(W, H)
    r.add_model(5, trimesh.creation.box(extents=(40.0, 25.0, 1e-3)))
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    try:
        for angle, t in ((0.0, [0.0, 0.0, 500.0]), (0.43, [21.0, -13.0, 610.0]), (2.2, [-30.0, 17.5, 450.0])):
            R = rot_z(angle)
            t = np.asarray(t)
            corners = np.array(
                [[-20.0, -12.5, -5e-4], [20.0, -12.5, -5e-4], [20.0, 12.5, -5e-4], [-20.0, 12.5, -5e-4]]
            )
            cam = corners @ R.T + t
            uv = (cam @ K.T)[:, :2] / cam[:, 2:]
            depth = r.render_depth(5, R, t, K)
            mask = depth > 0
            hand, dist = _inside_polygon(cols + 0.5, rows + 0.5, uv)
            clear = dist > 1e-3  # leave out pixel centres on an edge
            assert clear.mean() > 0.99
            assert np.array_equal(mask[clear], hand[clear]), (
                f"angle {angle}: {np.sum(mask[clear] != hand[clear])} pixels differ"
            )
            assert hand.sum() > 200
            # OpenCV's pixel centres (integer coordinates) are half a pixel away: many pixels differ
            opencv, _ = _inside_polygon(cols.astype(float), rows.astype(float), uv)
            assert np.sum(opencv != mask) > 20
            assert np.allclose(depth[mask], t[2] - 5e-4, atol=0.01)
    finally:
        r.close()


# ----------------------------------------------------------------------------- determinism, refusal
def _json_files(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): p.read_text() for p in sorted(root.rglob("*.json"))}


def test_same_seed_same_json_and_existing_out_refused(root: Path, tmp_path: Path) -> None:
    again = make_bop_fixture(tmp_path / "again", seed=0, **SIZES)
    assert _json_files(tmp_path / "again") == _json_files(root)
    ply = "models/obj_000003.ply"
    assert (tmp_path / "again" / ply).read_bytes() == (root / ply).read_bytes()
    assert again.seconds > 0
    before = _json_files(root)
    with pytest.raises(FixtureExistsError, match="already exists") as err:
        make_bop_fixture(root, seed=1, **SIZES)
    assert "\n" not in str(err.value) and isinstance(err.value, FileExistsError)
    assert _json_files(root) == before and not root.with_name(root.name + ".partial").exists()
    other = make_bop_fixture(tmp_path / "again", seed=1, overwrite=True, **SIZES)
    assert other.path == tmp_path / "again"
    assert (
        _json_files(tmp_path / "again")["train_pbr/000000/scene_gt.json"]
        != before["train_pbr/000000/scene_gt.json"]
    )


def test_camera_scales_the_tless_intrinsics() -> None:
    cam = camera(720, 540)
    assert (cam["fx"], cam["fy"], cam["cx"], cam["cy"]) == (1075.65, 1073.90, 373.06, 257.73)
    half = camera(360, 270)
    assert half["fx"] == pytest.approx(1075.65 / 2) and half["cy"] == pytest.approx(257.73 / 2)
