"""Reading a dataset in the BOP format (Hodaň et al., BOP 2018/2020; the layout of T-LESS):

.. code-block:: text

    <root>/
      models/models_info.json          {"<obj_id>": {"diameter", "min_x", …, "symmetries_discrete", "symmetries_continuous"}}
      models/obj_000001.ply …          meshes in mm
      models_eval/                     the evaluation meshes (optional; the models are used otherwise)
      <split>/<scene_id:06d>/          splits: train_pbr, train_primesense, test_primesense, …
        scene_gt.json                  {"<im_id>": [{"cam_R_m2c": 9, "cam_t_m2c": 3 (mm), "obj_id"}, …]}
        scene_camera.json              {"<im_id>": {"cam_K": 9, "depth_scale"}}
        scene_gt_info.json             {"<im_id>": [{"bbox_obj", "bbox_visib", "px_count_visib", "visib_fract"}, …]}
        rgb/<im_id:06d>.png|jpg   depth/<im_id:06d>.png   mask/ mask_visib/<im_id:06d>_<gt_idx:06d>.png
      test_targets_bop19.json          [{"scene_id", "im_id", "obj_id", "inst_count"}, …]

:class:`BopSplit` lists the ground-truth object instances of one split as :class:`Instance` records
(pose, box, visibility, file paths); images are read only when a sample is made. Missing files name
their path; a malformed JSON names the file and the key; objects without a ``models_info`` entry
are refused.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: what ``posediff data make-bop`` makes; the README's T-LESS section shows the real download.
MAKE_HINT = "posediff data make-bop out=<dir> makes a small one; see the README for T-LESS"


class BopFormatError(ValueError):
    """A BOP file is missing or malformed (the message is one line naming the file, and the key)."""


def read_json(path: Path) -> Any:
    """``json.load`` with one-line errors naming the file."""
    if not path.is_file():
        raise BopFormatError(f"missing BOP file {path} ({MAKE_HINT})")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise BopFormatError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None


def _get(entry: Any, key: str, path: Path, where: str, n: int | None = None) -> Any:
    """``entry[key]`` (as a float array of ``n`` numbers when ``n`` is given) or a one-line error."""
    if not isinstance(entry, dict) or key not in entry:
        raise BopFormatError(f"{path}: {where} has no key {key!r}")
    value = entry[key]
    if n is None:
        return value
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise BopFormatError(f"{path}: {where}[{key!r}] is not a list of numbers") from None
    if arr.size != n:
        raise BopFormatError(f"{path}: {where}[{key!r}] has {arr.size} numbers, not {n}")
    return arr


@dataclass(frozen=True, eq=False)
class Instance:
    """One ground-truth object instance of one image. ``R`` (3, 3), ``t`` (3,) mm model → camera
    (OpenCV); ``K`` (3, 3); boxes ``[x, y, w, h]`` in pixels (``bbox_obj`` the whole projected
    object, possibly outside the image; ``bbox_visib`` its visible part). Two instances are equal
    when they are the same ground truth (split, scene, image, index)."""

    split: str
    scene_id: int
    im_id: int
    gt_idx: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    depth_scale: float
    bbox_obj: np.ndarray
    bbox_visib: np.ndarray
    px_count_visib: int
    visib_fract: float
    scene_dir: Path = field(repr=False)
    rgb_ext: str = field(repr=False, default=".png")
    #: ``(H, W)`` of the scene's images
    image_hw: tuple[int, int] = field(repr=False, default=(0, 0))

    @property
    def rgb_path(self) -> Path:
        return self.scene_dir / "rgb" / f"{self.im_id:06d}{self.rgb_ext}"

    @property
    def depth_path(self) -> Path:
        return self.scene_dir / "depth" / f"{self.im_id:06d}.png"

    @property
    def mask_visib_path(self) -> Path:
        return self.scene_dir / "mask_visib" / f"{self.im_id:06d}_{self.gt_idx:06d}.png"

    @property
    def mask_path(self) -> Path:
        return self.scene_dir / "mask" / f"{self.im_id:06d}_{self.gt_idx:06d}.png"

    @property
    def key(self) -> tuple[int, int, int]:
        """``(scene_id, im_id, gt_idx)``."""
        return (self.scene_id, self.im_id, self.gt_idx)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Instance):
            return NotImplemented
        return (self.split, *self.key) == (other.split, *other.key)

    def __hash__(self) -> int:
        return hash((self.split, *self.key))


#: the per-instance columns of an :class:`InstanceTable` (besides the scene index)
_COLUMNS = ("scene_id", "im_id", "gt_idx", "obj_id", "R", "t", "K", "depth_scale", "bbox_obj", "bbox_visib",
            "px_count_visib", "visib_fract")  # fmt: skip


class InstanceTable(Sequence[Instance]):
    """Ground-truth instances stored as numpy columns (a million T-LESS PBR instances take ~0.3 GB
    and are shared, not copied, by forked ``DataLoader`` workers); indexing yields
    :class:`Instance` records, slicing / :meth:`take` a smaller table. Columns are attributes:
    ``obj_id (N,)``, ``R (N, 3, 3)``, ``t (N, 3)``, ``bbox_obj (N, 4)``, ``visib_fract (N,)`` …
    ``scenes`` lists ``(split, scene folder, rgb extension, (H, W))``; ``scene`` indexes it."""

    def __init__(self, scenes: list[tuple[str, Path, str, tuple[int, int]]], columns: dict[str, np.ndarray]):
        self.scenes = scenes
        self.scene = np.asarray(columns["scene"], dtype=np.int32)
        for name in _COLUMNS:
            setattr(self, name, columns[name])

    @classmethod
    def empty(cls) -> InstanceTable:
        shapes = {"R": (0, 3, 3), "t": (0, 3), "K": (0, 3, 3), "bbox_obj": (0, 4), "bbox_visib": (0, 4)}
        cols = {n: np.zeros(shapes.get(n, (0,))) for n in _COLUMNS}
        for n in ("scene_id", "im_id", "gt_idx", "obj_id", "px_count_visib"):
            cols[n] = cols[n].astype(np.int64)
        return cls([], {"scene": np.zeros(0, dtype=np.int32), **cols})

    @classmethod
    def concat(cls, tables: Sequence[InstanceTable]) -> InstanceTable:
        """One table of several (their scene lists joined)."""
        tables = [t for t in tables if len(t)]
        if not tables:
            return cls.empty()
        scenes: list[tuple[str, Path, str, tuple[int, int]]] = []
        offsets = []
        for t in tables:
            offsets.append(len(scenes))
            scenes.extend(t.scenes)
        cols = {n: np.concatenate([getattr(t, n) for t in tables]) for n in _COLUMNS}
        cols["scene"] = np.concatenate([t.scene + o for t, o in zip(tables, offsets, strict=True)])
        return cls(scenes, cols)

    def take(self, index: Any) -> InstanceTable:
        """The instances at ``index`` (integer array, boolean mask or slice), as a table."""
        cols = {n: getattr(self, n)[index] for n in _COLUMNS}
        cols["scene"] = self.scene[index]
        return InstanceTable(self.scenes, cols)

    def __len__(self) -> int:
        return len(self.scene)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return self.take(i)
        i = int(i)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"instance {i} of {len(self)}")
        split, scene_dir, ext, hw = self.scenes[int(self.scene[i])]
        return Instance(
            split=split,
            scene_id=int(self.scene_id[i]),
            im_id=int(self.im_id[i]),
            gt_idx=int(self.gt_idx[i]),
            obj_id=int(self.obj_id[i]),
            R=self.R[i],
            t=self.t[i],
            K=self.K[i],
            depth_scale=float(self.depth_scale[i]),
            bbox_obj=self.bbox_obj[i],
            bbox_visib=self.bbox_visib[i],
            px_count_visib=int(self.px_count_visib[i]),
            visib_fract=float(self.visib_fract[i]),
            scene_dir=scene_dir,
            rgb_ext=ext,
            image_hw=hw,
        )

    @property
    def image_hw(self) -> np.ndarray:
        """``(N, 2)`` image sizes."""
        hw = np.array([s[3] for s in self.scenes], dtype=np.float64).reshape(-1, 2)
        return hw[self.scene]


class BopModels:
    """The object models of a BOP dataset: ``models_info.json`` (diameters, symmetries) and meshes.

    ``models_dir`` is relative to ``root`` (``models``; real T-LESS also ships ``models_cad`` and
    ``models_reconst``); ``eval_models_dir`` (``models_eval``) is used for the evaluation points when
    present.
    """

    def __init__(self, root: str | Path, models_dir: str = "models", eval_models_dir: str = "models_eval"):
        self.root = Path(root)
        self.dir = self.root / models_dir
        if not self.dir.is_dir():
            raise BopFormatError(f"missing BOP models folder {self.dir} ({MAKE_HINT})")
        self.info_path = self.dir / "models_info.json"
        raw = read_json(self.info_path)
        if not isinstance(raw, dict):
            raise BopFormatError(f"{self.info_path}: expected an object keyed by object id")
        self.info: dict[int, dict[str, Any]] = {}
        for key, entry in raw.items():
            try:
                obj_id = int(key)
            except ValueError:
                raise BopFormatError(f"{self.info_path}: key {key!r} is not an object id") from None
            d = float(_get(entry, "diameter", self.info_path, f"object {key}"))
            if not d > 0:
                raise BopFormatError(f"{self.info_path}: object {key} has diameter {d}")
            self.info[obj_id] = dict(entry)
        eval_dir = self.root / eval_models_dir
        self.eval_dir = eval_dir if eval_dir.is_dir() else self.dir
        #: the evaluation models' entries (the BOP toolkit reads models_eval/models_info.json); the
        #: training models' where that folder or file is absent
        self.eval_info = self.info
        eval_info_path = self.eval_dir / "models_info.json"
        if self.eval_dir != self.dir and eval_info_path.is_file():
            raw_eval = read_json(eval_info_path)
            self.eval_info = (
                {int(k): dict(v) for k, v in raw_eval.items()} if isinstance(raw_eval, dict) else {}
            )
            missing = sorted(set(self.info) - set(self.eval_info))
            if missing:
                raise BopFormatError(
                    f"{eval_info_path}: no entry for object(s) {missing} of {self.info_path}"
                )

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.info)

    def check(self, obj_ids: Iterable[int], where: str) -> None:
        """Refuse object ids without a ``models_info`` entry."""
        missing = sorted({int(o) for o in obj_ids} - set(self.info))
        if missing:
            raise BopFormatError(
                f"{where}: object id(s) {missing} have no entry in {self.info_path} (it has {self.obj_ids})"
            )

    def diameter(self, obj_id: int, evaluation: bool = False) -> float:
        """The object's diameter (mm), from the evaluation models' info with ``evaluation``."""
        return float((self.eval_info if evaluation else self.info)[int(obj_id)]["diameter"])

    def mesh_path(self, obj_id: int, evaluation: bool = False) -> Path:
        path = (self.eval_dir if evaluation else self.dir) / f"obj_{int(obj_id):06d}.ply"
        if not path.is_file():
            raise BopFormatError(f"missing BOP model {path}")
        return path

    @functools.cache  # noqa: B019 - one per dataset object, lives as long as it
    def mesh(self, obj_id: int, evaluation: bool = False):  # noqa: ANN201 - trimesh.Trimesh
        import trimesh

        return trimesh.load(self.mesh_path(obj_id, evaluation), force="mesh", process=False)

    def points(self, obj_id: int) -> np.ndarray:
        """``(N, 3)`` float64 vertices of the evaluation model (mm): the BOP metrics' point set."""
        return np.asarray(self.mesh(int(obj_id), True).vertices, dtype=np.float64)

    def symmetries(
        self, obj_id: int, max_sym_disc_step: float = 0.01, evaluation: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """The BOP symmetry set ``(R (S, 3, 3), t (S, 3))`` of an object
        (:func:`posediff.metrics.bop.symmetry_transforms`), of the evaluation models with ``evaluation``."""
        return _symmetries(self, int(obj_id), float(max_sym_disc_step), bool(evaluation))


@functools.cache
def _symmetries(
    models: BopModels, obj_id: int, step: float, evaluation: bool
) -> tuple[np.ndarray, np.ndarray]:
    from ...metrics.bop import symmetry_transforms

    return symmetry_transforms((models.eval_info if evaluation else models.info)[obj_id], step)


def scene_dirs(split_dir: Path) -> list[Path]:
    """The scene folders of a split (six-digit names), sorted."""
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit())


def _rgb_format(scene_dir: Path) -> tuple[str, tuple[int, int]]:
    """The rgb file extension of a scene and its image size ``(H, W)`` (from its first image)."""
    import cv2

    for ext in (".png", ".jpg", ".jpeg", ".tif"):
        first = next((scene_dir / "rgb").glob(f"*{ext}"), None)
        if first is not None:
            img = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise BopFormatError(f"cannot read image {first}")
            return ext, (int(img.shape[0]), int(img.shape[1]))
    raise BopFormatError(f"no rgb images in {scene_dir / 'rgb'}")


class BopSplit:
    """The ground-truth instances of one split (``root/<split>``), optionally of some objects only.

    ``images``: a set of ``(scene_id, im_id)`` to keep (e.g. the images of ``test_targets_bop19.json``).
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        models: BopModels,
        *,
        obj_ids: Sequence[int] | None = None,
        images: set[tuple[int, int]] | None = None,
    ) -> None:
        self.root, self.split = Path(root), split
        self.dir = self.root / split
        if not self.dir.is_dir():
            available = (
                sorted(p.name for p in self.root.iterdir() if p.is_dir()) if self.root.is_dir() else []
            )
            raise BopFormatError(
                f"missing BOP split {self.dir} (folders there: {', '.join(available) or 'none'}; {MAKE_HINT})"
            )
        keep = None if obj_ids is None else {int(o) for o in obj_ids}
        self._scenes: list[tuple[str, Path, str, tuple[int, int]]] = []
        self._rows: dict[str, list[Any]] = {n: [] for n in ("scene", *_COLUMNS)}
        for scene_dir in scene_dirs(self.dir):
            self._read_scene(scene_dir, models, keep, images)
        rows, self._rows = self._rows, {}
        if not rows["scene"]:
            self.instances = InstanceTable.empty()
            return
        cols = {n: np.asarray(v) for n, v in rows.items()}
        cols["R"], cols["K"] = cols["R"].reshape(-1, 3, 3), cols["K"].reshape(-1, 3, 3)
        #: the split's instances (an :class:`InstanceTable`)
        self.instances = InstanceTable(self._scenes, cols)

    def _read_scene(
        self,
        scene_dir: Path,
        models: BopModels,
        keep: set[int] | None,
        images: set[tuple[int, int]] | None,
    ) -> None:
        scene_id = int(scene_dir.name)
        gt_path, cam_path, info_path = (
            scene_dir / f for f in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json")
        )
        gt, cam, info = read_json(gt_path), read_json(cam_path), read_json(info_path)
        ext, hw = _rgb_format(scene_dir)
        scene = len(self._scenes)
        self._scenes.append((self.split, scene_dir, ext, hw))
        rows = self._rows
        for im_key, gts in gt.items():
            im_id = int(im_key)
            if images is not None and (scene_id, im_id) not in images:
                continue
            if im_key not in cam:
                raise BopFormatError(f"{cam_path}: no entry for image {im_key}")
            if im_key not in info:
                raise BopFormatError(f"{info_path}: no entry for image {im_key}")
            K = _get(cam[im_key], "cam_K", cam_path, f"image {im_key}", 9)
            depth_scale = float(cam[im_key].get("depth_scale", 1.0))
            infos = info[im_key]
            if len(infos) != len(gts):
                raise BopFormatError(
                    f"{info_path}: image {im_key} lists {len(infos)} instances, {gt_path} lists {len(gts)}"
                )
            for k, (g, gi) in enumerate(zip(gts, infos, strict=True)):
                where = f"image {im_key} instance {k}"
                obj_id = int(_get(g, "obj_id", gt_path, where))
                if keep is not None and obj_id not in keep:
                    continue
                if obj_id not in models.info:
                    raise BopFormatError(
                        f"{gt_path}: {where} is object {obj_id}, which has no entry in {models.info_path}"
                    )
                for name, value in (
                    ("scene", scene),
                    ("scene_id", scene_id),
                    ("im_id", im_id),
                    ("gt_idx", k),
                    ("obj_id", obj_id),
                    ("R", _get(g, "cam_R_m2c", gt_path, where, 9)),
                    ("t", _get(g, "cam_t_m2c", gt_path, where, 3)),
                    ("K", K),
                    ("depth_scale", depth_scale),
                    ("bbox_obj", _get(gi, "bbox_obj", info_path, where, 4)),
                    ("bbox_visib", _get(gi, "bbox_visib", info_path, where, 4)),
                    ("px_count_visib", int(_get(gi, "px_count_visib", info_path, where))),
                    ("visib_fract", float(_get(gi, "visib_fract", info_path, where))),
                ):
                    rows[name].append(value)

    def __len__(self) -> int:
        return len(self.instances)


@dataclass(frozen=True)
class Target:
    """One BOP19 test target: ``inst_count`` instances of ``obj_id`` in image ``(scene_id, im_id)``."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def read_targets(path: str | Path) -> list[Target]:
    """The entries of a ``test_targets_bop19.json``."""
    path = Path(path)
    raw = read_json(path)
    if not isinstance(raw, list):
        raise BopFormatError(f"{path}: expected a list of targets")
    out = []
    for k, entry in enumerate(raw):
        vals = [
            int(_get(entry, key, path, f"target {k}"))
            for key in ("scene_id", "im_id", "obj_id", "inst_count")
        ]
        out.append(Target(*vals))
    return out


def target_instances(instances: Sequence[Instance], targets: Sequence[Target]) -> list[Instance]:
    """The ground-truth instances the BOP19 protocol scores: for each target, the ``inst_count`` most
    visible instances of its object in its image (the toolkit's ``visib_gt_min = -1``)."""
    by_key: dict[tuple[int, int, int], list[Instance]] = {}
    for inst in instances:
        by_key.setdefault((inst.scene_id, inst.im_id, inst.obj_id), []).append(inst)
    out = []
    for t in targets:
        cands = sorted(by_key.get((t.scene_id, t.im_id, t.obj_id), []), key=lambda i: -i.visib_fract)
        out.extend(cands[: t.inst_count])
    return out


def read_rgb(path: Path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BopFormatError(f"cannot read image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_mask(path: Path) -> np.ndarray:
    """``(H, W)`` bool."""
    import cv2

    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise BopFormatError(f"cannot read mask {path}")
    return m > 0 if m.ndim == 2 else m[..., 0] > 0


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """``(H, W)`` float32 depth in mm (the stored 16-bit value × ``depth_scale``; 0 = no measurement)."""
    import cv2

    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise BopFormatError(f"cannot read depth {path}")
    return d.astype(np.float32) * np.float32(depth_scale)


__all__ = [
    "BopFormatError",
    "BopModels",
    "BopSplit",
    "Instance",
    "InstanceTable",
    "Target",
    "read_depth",
    "read_json",
    "read_mask",
    "read_rgb",
    "read_targets",
    "target_instances",
]
