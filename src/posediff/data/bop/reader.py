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
(pose, box, visibility, file paths); images are decoded only when a sample is made. Missing files name
their path; a malformed JSON names the file and the key; objects without a ``models_info`` entry
or without a finite positive ``diameter`` (in ``models/`` or ``models_eval/``) are refused.

Reading a split checks up front (:meth:`BopSplit.check_files`), from folder listings and image
headers only (no decoding), that every file its instances need is there and sound: the colour
image (``rgb/``, or ``gray/``) and ``mask_visib`` of every instance, and its depth map where the
split needs depth (:attr:`BopSplit.require_depth`: a ``test*`` / ``val*`` split whose cameras give
a ``depth_scale``, for VSD); that images, depth maps and the masks of test splits (those of
training splits only for presence: a million in T-LESS PBR) are not truncated, not over PIL's
decompression-bomb limit, of a usable kind (colour: 8- or 16-bit grey or RGB; depth: a 16-bit grey
PNG) and of the split's size (the root's ``camera_<sensor>.json`` / ``camera.json`` for a test
split, else the size most of the split's images have). Problems are reported in one line naming
the first file, its scene and image, and how many more files of the split are affected.
:func:`read_rgb`, :func:`read_mask` and :func:`read_depth` make the same checks on the bytes they
decode and raise :class:`BopFormatError` naming the file.
"""

from __future__ import annotations

import functools
import io
import json
import math
import os
import warnings
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...symmetry import SymmetrySet

#: what ``posediff data make-bop`` makes; docs/bop.md shows the real download.
MAKE_HINT = "posediff data make-bop out=<dir> makes a small one; see docs/bop.md for T-LESS"


class BopFormatError(ValueError):
    """A BOP file is missing or malformed (the message is one line naming the file, and the key)."""


#: the folders of a scene's colour images: ``rgb/``, or ``gray/`` in grey-only datasets (ITODD)
IMAGE_DIRS = ("rgb", "gray")
#: colour image extensions, in the order of preference when a folder mixes them
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
#: PIL modes of colour images that decode to 8-bit BGR (OpenCV scales 16-bit samples to 8 bits)
COLOUR_MODES = frozenset({"1", "L", "LA", "P", "PA", "RGB", "RGBA", "I;16", "I;16B", "I;16L"})
#: PIL modes of masks (anything non-zero is the object)
MASK_MODES = COLOUR_MODES
#: bytes at the end of a file searched for the PNG ``IEND`` chunk / the JPEG end-of-image marker
_TAIL = 1024


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


def _diameter(entry: Any, path: Path, key: str) -> float:
    """The finite positive ``diameter`` of a ``models_info`` entry, or a one-line error."""
    hint = "every object needs its diameter in mm (re-extract the models or restore the entry)"
    if not isinstance(entry, dict) or "diameter" not in entry:
        raise BopFormatError(f"{path}: object {key} has no 'diameter'; {hint}")
    try:
        d = float(entry["diameter"])
    except (TypeError, ValueError):
        d = math.nan
    if not (math.isfinite(d) and d > 0):
        raise BopFormatError(f"{path}: object {key} has diameter {entry['diameter']!r}; {hint}")
    return d


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
    #: the folder of the colour images in ``scene_dir``: ``rgb`` (``gray`` in grey-only datasets)
    image_dir: str = field(repr=False, default="rgb")

    @property
    def rgb_path(self) -> Path:
        return self.scene_dir / self.image_dir / f"{self.im_id:06d}{self.rgb_ext}"

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


#: a scene of an :class:`InstanceTable`: ``(split, scene folder, rgb extension, (H, W), image folder)``
Scene = tuple[str, Path, str, tuple[int, int], str]

#: the per-instance columns of an :class:`InstanceTable` (besides the scene index)
_COLUMNS = ("scene_id", "im_id", "gt_idx", "obj_id", "R", "t", "K", "depth_scale", "bbox_obj", "bbox_visib",
            "px_count_visib", "visib_fract")  # fmt: skip


class InstanceTable(Sequence[Instance]):
    """Ground-truth instances stored as numpy columns (a million T-LESS PBR instances take ~0.3 GB
    and are shared, not copied, by forked ``DataLoader`` workers); indexing yields
    :class:`Instance` records, slicing / :meth:`take` a smaller table. Columns are attributes:
    ``obj_id (N,)``, ``R (N, 3, 3)``, ``t (N, 3)``, ``bbox_obj (N, 4)``, ``visib_fract (N,)`` …
    ``scenes`` lists ``(split, scene folder, rgb extension, (H, W), image folder)``; ``scene`` indexes it."""

    def __init__(self, scenes: list[Scene], columns: dict[str, np.ndarray]):
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
        scenes: list[Scene] = []
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
        split, scene_dir, ext, hw, image_dir = self.scenes[int(self.scene[i])]
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
            image_dir=image_dir,
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
            _diameter(entry, self.info_path, key)
            self.info[obj_id] = dict(entry)
        eval_dir = self.root / eval_models_dir
        self.eval_dir = eval_dir if eval_dir.is_dir() else self.dir
        #: the evaluation models' entries (the BOP toolkit reads models_eval/models_info.json); the
        #: training models' where that folder or file is absent
        self.eval_info = self.info
        eval_info_path = self.eval_dir / "models_info.json"
        if self.eval_dir != self.dir and eval_info_path.is_file():
            raw_eval = read_json(eval_info_path)
            if not isinstance(raw_eval, dict):
                raise BopFormatError(f"{eval_info_path}: expected an object keyed by object id")
            self.eval_info = {}
            for key, entry in raw_eval.items():
                try:
                    self.eval_info[int(key)] = dict(entry)
                except (TypeError, ValueError):
                    raise BopFormatError(
                        f"{eval_info_path}: entry {key!r} is not an object id with a models_info entry"
                    ) from None
            missing = sorted(set(self.info) - set(self.eval_info))
            if missing:
                raise BopFormatError(
                    f"{eval_info_path}: no entry for object(s) {missing} of {self.info_path}"
                )
            for obj_id in self.info:  # the objects used: their evaluation diameters (MSSD, VSD)
                _diameter(self.eval_info[obj_id], eval_info_path, str(obj_id))

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

    def symmetry_set(self, obj_id: int, evaluation: bool = False) -> SymmetrySet:
        """The object's :class:`~posediff.symmetry.SymmetrySet` (from ``models_info``; of the evaluation
        models with ``evaluation``)."""
        return _symmetry_set(self, int(obj_id), bool(evaluation))

    def symmetries(
        self, obj_id: int, max_sym_disc_step: float = 0.01, evaluation: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """The discretised BOP symmetry set ``(R (S, 3, 3), t (S, 3))`` of an object
        (:meth:`SymmetrySet.transforms`), of the evaluation models with ``evaluation``."""
        return self.symmetry_set(obj_id, evaluation).transforms(float(max_sym_disc_step))


@functools.cache
def _symmetry_set(models: BopModels, obj_id: int, evaluation: bool) -> SymmetrySet:
    info = models.eval_info if evaluation else models.info
    return SymmetrySet.from_models_info(info[obj_id], name=f"obj_{obj_id:06d}")


# ------------------------------------------------------------------------------------ image checks
#: the hint of a missing file
MISSING_HINT = "re-extract the split or drop the scene"


@dataclass(frozen=True)
class _Problem:
    """What is wrong with one file: ``label`` counts it (``missing``, ``truncated`` …), ``text``
    follows its path, ``hint`` says what to do."""

    label: str
    text: str
    hint: str = "re-extract it"


def _error_text(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0].rstrip(".")


def _rawmode(im: Any) -> str:
    """The raw mode of the first tile of a PIL image (``"RGB;16B"`` for a 16-bit RGB PNG), or ``""``."""
    tile = getattr(im, "tile", None) or []
    if not tile:
        return ""
    args = getattr(tile[0], "args", None)
    if args is None and isinstance(tile[0], tuple) and len(tile[0]) > 3:
        args = tile[0][3]
    if isinstance(args, tuple):
        args = args[0] if args else ""
    return args if isinstance(args, str) else ""


def _inspect(f: Any, nbytes: int, kind: str) -> tuple[tuple[int, int] | None, _Problem | None]:
    """``((H, W), problem)`` of the image in the binary file ``f`` of ``nbytes`` bytes, from its header
    and its last bytes only (nothing is decoded). ``kind``: ``rgb`` (a colour or grey image),
    ``mask`` or ``depth`` (a 16-bit grey PNG)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(f)
            fmt, mode, (w, h), rawmode = str(im.format), str(im.mode), im.size, _rawmode(im)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        return None, _Problem(
            "too large",
            f"is over PIL's decompression-bomb limit ({_error_text(e)})",
            "BOP images have a few megapixels: re-extract it",
        )
    except Exception as e:  # noqa: BLE001 - PIL raises OSError, SyntaxError, struct.error … on broken headers
        return None, _Problem("unreadable", f"is not a readable image ({_error_text(e)})")
    hw = (int(h), int(w))
    if fmt in ("PNG", "JPEG"):
        f.seek(max(0, nbytes - _TAIL))
        end, what = (b"IEND", "IEND chunk") if fmt == "PNG" else (b"\xff\xd9", "end-of-image marker")
        if end not in f.read():
            return hw, _Problem("truncated", f"is truncated (a {fmt} without its {what})")
    bits = " with 16-bit samples" if ";16" in rawmode or mode.startswith("I;16") else ""
    if kind == "depth":
        if fmt != "PNG" or not (mode.startswith("I;16") or rawmode.startswith("I;16")):
            return hw, _Problem(
                "not 16-bit depth",
                f"is a {fmt} of mode {mode}{bits}, not a 16-bit grey PNG",
                "BOP depth maps are uint16 PNGs (mm = value x depth_scale): re-extract it",
            )
    elif mode not in (COLOUR_MODES if kind == "rgb" else MASK_MODES):
        what = "a colour image" if kind == "rgb" else "a mask"
        return hw, _Problem(
            "of an odd mode",
            f"is a {fmt} of mode {mode}{bits}, which cannot be read as {what}",
            "colour images and masks must be 8- or 16-bit grey or RGB(A): convert it or re-extract it",
        )
    return hw, None


def inspect_image(path: Path, kind: str = "rgb") -> tuple[tuple[int, int] | None, _Problem | None]:
    """``((H, W), problem)`` of an image file from its header and last bytes (:func:`_inspect`)."""
    try:
        with open(path, "rb") as f:
            return _inspect(f, os.fstat(f.fileno()).st_size, kind)
    except FileNotFoundError:
        return None, _Problem("missing", "is missing", MISSING_HINT)
    except OSError as e:
        return None, _Problem("unreadable", f"cannot be read ({e.strerror or type(e).__name__})")


def _decode(path: Path, flags: int, kind: str) -> np.ndarray:
    """The image at ``path`` decoded by OpenCV with ``flags``, after the checks of :func:`_inspect`
    on its bytes; a :class:`BopFormatError` naming the file otherwise."""
    import cv2

    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise BopFormatError(f"{path} is missing; {MISSING_HINT}") from None
    except OSError as e:
        raise BopFormatError(f"{path} cannot be read ({e.strerror or type(e).__name__})") from None
    _, problem = _inspect(io.BytesIO(data), len(data), kind)
    if problem is not None:
        raise BopFormatError(f"{path} {problem.text}; {problem.hint}")
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as e:
        raise BopFormatError(f"{path}: OpenCV cannot decode it ({_error_text(e)}); re-extract it") from None
    if img is None:
        raise BopFormatError(f"{path}: OpenCV cannot decode it; re-extract it")
    return img


def scene_dirs(split_dir: Path) -> list[Path]:
    """The scene folders of a split (six-digit names), sorted."""
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit())


def _listing(folder: Path) -> set[str] | None:
    """The file names in ``folder`` (``None`` when it is not a folder)."""
    try:
        with os.scandir(folder) as it:
            return {e.name for e in it}
    except (FileNotFoundError, NotADirectoryError):
        return None


def _image_format(scene_dir: Path) -> tuple[str, str, set[str]]:
    """``(folder, extension, file names)`` of a scene's colour images (``rgb/``, else ``gray/``)."""
    for folder in IMAGE_DIRS:
        names = _listing(scene_dir / folder)
        for ext in IMAGE_EXTS if names else ():
            if any(n.endswith(ext) for n in names):
                return folder, ext, names
    raise BopFormatError(f"no rgb images in {scene_dir / 'rgb'}")


def _is_evaluation_split(split: str) -> bool:
    """Whether a split is scored (BOP's ``test*`` and ``val*`` splits), not trained on."""
    return split.startswith(("test", "val"))


class BopSplit:
    """The ground-truth instances of one split (``root/<split>``), optionally of some objects only.

    ``images``: a set of ``(scene_id, im_id)`` to keep (e.g. the images of ``test_targets_bop19.json``).
    ``check``: verify the instances' files on construction (:meth:`check_files`; module docstring).
    ``require_depth``: whether every instance needs its depth map (VSD); ``None`` decides from the
    split: a ``test*`` / ``val*`` split whose ``scene_camera.json`` gives a ``depth_scale``.
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        models: BopModels,
        *,
        obj_ids: Sequence[int] | None = None,
        images: set[tuple[int, int]] | None = None,
        check: bool = True,
        require_depth: bool | None = None,
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
        #: a scored split (``test*`` / ``val*``): its masks are checked to the header, its images
        #: against the root's camera file
        self.evaluation = _is_evaluation_split(split)
        keep = None if obj_ids is None else {int(o) for o in obj_ids}
        self._scenes: list[Scene] = []
        self._names: dict[Path, set[str]] = {}
        self._depth_scale = False
        self._rows: dict[str, list[Any]] = {n: [] for n in ("scene", *_COLUMNS)}
        for scene_dir in scene_dirs(self.dir):
            self._read_scene(scene_dir, models, keep, images)
        #: whether the instances' depth maps are checked (module docstring)
        self.require_depth = (
            bool(require_depth) if require_depth is not None else self.evaluation and self._depth_scale
        )
        rows, self._rows = self._rows, {}
        if not rows["scene"]:
            self.instances = InstanceTable.empty()
            self._names = {}
            return
        cols = {n: np.asarray(v) for n, v in rows.items()}
        cols["R"], cols["K"] = cols["R"].reshape(-1, 3, 3), cols["K"].reshape(-1, 3, 3)
        #: the split's instances (an :class:`InstanceTable`)
        self.instances = InstanceTable(self._scenes, cols)
        try:
            if check:
                self.check_files()
            else:
                self._first_image_sizes()
        finally:
            self._names = {}

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
        folder, ext, names = _image_format(scene_dir)
        self._names[scene_dir / folder] = names
        scene = len(self._scenes)
        self._scenes.append((self.split, scene_dir, ext, (0, 0), folder))
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
            self._depth_scale |= isinstance(cam[im_key], dict) and "depth_scale" in cam[im_key]
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

    def _names_in(self, folder: Path) -> set[str]:
        if folder not in self._names:
            self._names[folder] = _listing(folder) or set()
        return self._names[folder]

    def _first_image_sizes(self) -> None:
        """Each scene's image size from its first image (what ``check=False`` reads)."""
        for k, (split, scene_dir, ext, _, folder) in enumerate(self._scenes):
            first = min(n for n in self._names_in(scene_dir / folder) if n.endswith(ext))
            path = scene_dir / folder / first
            hw, problem = inspect_image(path)
            if hw is None or problem is not None:
                p = problem or _Problem("unreadable", "is not a readable image")
                raise BopFormatError(f"{path} {p.text}; {p.hint}")
            self._scenes[k] = (split, scene_dir, ext, hw, folder)

    def camera_size(self) -> tuple[tuple[int, int], Path] | None:
        """``((H, W), file)`` from the root's camera file of this split's sensor
        (``camera_<sensor>.json`` for ``<kind>_<sensor>``, else ``camera.json``), or ``None``."""
        sensor = self.split.split("_", 1)[1] if "_" in self.split else ""
        for name in ([f"camera_{sensor}.json"] if sensor else []) + ["camera.json"]:
            path = self.root / name
            if path.is_file():
                cam = read_json(path)
                try:
                    return (int(cam["height"]), int(cam["width"])), path
                except (TypeError, KeyError, ValueError):
                    raise BopFormatError(f"{path}: no whole 'width' and 'height' (the image size)") from None
        return None

    def check_files(self) -> None:
        """Verify every file the instances need (module docstring) from folder listings and image
        headers, and set each scene's image size; raise one :class:`BopFormatError` naming the first
        bad file, its scene and image, and how many more files of the split are affected."""
        inst = self.instances
        if not len(inst):
            return
        scenes = inst.scenes
        #: (scene position, im id, gt idx, path, problem)
        problems: list[tuple[int, int, int, Path, _Problem]] = []
        #: (scene position, im id, gt idx, path, (H, W), is a colour image) of the headers read
        sized: list[tuple[int, int, int, Path, tuple[int, int], bool]] = []

        def look(k: int, im: int, g: int, folder: Path, name: str, kind: str, header: bool) -> None:
            path = folder / name
            if name not in self._names_in(folder):
                problems.append((k, im, g, path, _Problem("missing", "is missing", MISSING_HINT)))
            elif header:
                hw, problem = inspect_image(path, kind)
                if problem is not None:
                    problems.append((k, im, g, path, problem))
                elif hw is not None:
                    sized.append((k, im, g, path, hw, kind == "rgb"))

        for k, (_, scene_dir, ext, _, folder) in enumerate(scenes):
            rows = np.flatnonzero(inst.scene == k)
            if not rows.size:
                continue
            im_ids, gt_idx = inst.im_id[rows].tolist(), inst.gt_idx[rows].tolist()
            for im in sorted(set(im_ids)):
                look(k, im, -1, scene_dir / folder, f"{im:06d}{ext}", "rgb", True)
                if self.require_depth:
                    look(k, im, -1, scene_dir / "depth", f"{im:06d}.png", "depth", True)
            masks = scene_dir / "mask_visib"
            for im, g in zip(im_ids, gt_idx, strict=True):
                look(k, im, g, masks, f"{im:06d}_{g:06d}.png", "mask", self.evaluation)

        colour = Counter(hw for *_, hw, is_colour in sized if is_colour)
        expected: tuple[int, int] | None = None
        camera = self.camera_size() if self.evaluation else None
        if camera is not None:
            expected, source = camera[0], f"{camera[1].name} says"
            hint = f"re-extract it, or fix {camera[1].name} if the split was resized on purpose"
        elif colour:
            expected, source = colour.most_common(1)[0][0], f"most images of {self.split} are"
            hint = "re-extract it, or resize it (and its masks and depth map) to the split's size"
        if expected is not None:
            H, W = expected
            for k, im, g, path, (h, w), _ in sized:
                if (h, w) != expected:
                    text = f"is {w}x{h} pixels, not {W}x{H} as {source}"
                    problems.append((k, im, g, path, _Problem("of the wrong size", text, hint)))
            for k, (split, scene_dir, ext, _, folder) in enumerate(scenes):
                scenes[k] = (split, scene_dir, ext, expected, folder)
        if problems:
            problems.sort(key=lambda p: (p[0], p[1], p[2], str(p[3])))
            k, im, g, path, first = problems[0]
            where = f"scene {int(scenes[k][1].name)} image {im}" + (f" instance {g}" if g >= 0 else "")
            others = Counter(p[4].label for p in problems[1:])
            if others:
                n = len(problems) - 1
                where += f"; and {n} more file{'s' if n > 1 else ''} of {self.split}"
                if set(others) != {first.label}:
                    where += ": " + ", ".join(f"{c} {label}" for label, c in others.items())
            raise BopFormatError(f"{path} {first.text} ({where}); {first.hint}")

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
    """``(H, W, 3)`` uint8 RGB (grey images repeated; 16-bit samples scaled to 8 bits)."""
    import cv2

    return cv2.cvtColor(_decode(path, cv2.IMREAD_COLOR, "rgb"), cv2.COLOR_BGR2RGB)


def read_mask(path: Path) -> np.ndarray:
    """``(H, W)`` bool."""
    import cv2

    m = _decode(path, cv2.IMREAD_UNCHANGED, "mask")
    return m > 0 if m.ndim == 2 else m[..., 0] > 0


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """``(H, W)`` float32 depth in mm (the stored 16-bit value × ``depth_scale``; 0 = no measurement)."""
    import cv2

    d = _decode(path, cv2.IMREAD_UNCHANGED, "depth")
    if d.dtype != np.uint16 or d.ndim != 2:
        raise BopFormatError(
            f"{path} decodes to {d.dtype} {d.shape}, not a 16-bit grey depth map; re-extract it"
        )
    return d.astype(np.float32) * np.float32(depth_scale)


__all__ = [
    "BopFormatError",
    "BopModels",
    "BopSplit",
    "Instance",
    "InstanceTable",
    "Target",
    "inspect_image",
    "read_depth",
    "read_json",
    "read_mask",
    "read_rgb",
    "read_targets",
    "target_instances",
]
