"""BOP datasets as per-instance crops: a PyTorch ``Dataset`` and a Lightning ``DataModule``.

As the paper (§5.3) and the authors' code: one sample per ground-truth object instance, the square
region of interest around its box (Dynamic Zoom-In in training, :mod:`.roi`), resized to
``image_size``, masked to the instance's visible pixels (the paper assumes ground-truth boxes and
visible masks, at test too), hard colour augmentation of training crops on the batch
(:class:`.augment.HardAugment`, kornia), and the pose encoded for the network by
:class:`.encoding.PoseEncoding` (standardised SITE translation, allocentric or egocentric rotation).

Instances are dropped when their visible box is ≤ 1 px wide or high or they have ≤ ``min_visible_px``
visible pixels (the authors' 64) or a visible fraction below ``min_visib_fract``; dropped test
targets are counted (``skipped``) and scored as misses.

A sample is a dict: ``image`` (3, S, S) float32 in [0, 1]; ``mask`` (S, S) bool (visible pixels);
``pose`` the diffusion target — ``[R_net | δ̂]`` (4, 4) for se3 / r3so3, ``R_net`` (3, 3) for so3;
``rotation`` (3, 3) and ``translation`` (3,) the camera-frame ground truth (mm); ``K`` (3, 3) the
image's intrinsics; ``centre`` (2,) and ``side`` () the crop in image pixels; ``obj_id``,
``scene_id``, ``im_id``, ``gt_idx``, ``index`` (into :attr:`BopInstanceDataset.instances`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from ...lie import LieGroup, get_group
from ..resumable import ResumableDataLoader, eval_loader
from .encoding import PoseEncoding
from .reader import (
    BopFormatError,
    BopModels,
    BopSplit,
    Instance,
    InstanceTable,
    read_mask,
    read_rgb,
    read_targets,
    target_instances,
)
from .roi import clip_box, clip_boxes, crop, dzi, dzi_many


def _keep(
    bbox_visib: Any, px_count_visib: Any, visib_fract: Any, min_visible_px: int, min_visib_fract: float
) -> Any:
    """The instance filter (module docstring) on scalars or arrays: ``bbox_visib (…, 4)``."""
    return (
        (bbox_visib[..., 2] > 1)
        & (bbox_visib[..., 3] > 1)
        & (px_count_visib > min_visible_px)
        & (visib_fract >= min_visib_fract)
    )


def keep_instance(inst: Instance, min_visible_px: int, min_visib_fract: float) -> bool:
    """The instance filter (module docstring)."""
    return bool(
        _keep(inst.bbox_visib, inst.px_count_visib, inst.visib_fract, min_visible_px, min_visib_fract)
    )


def keep_mask(table: InstanceTable, min_visible_px: int, min_visib_fract: float) -> np.ndarray:
    """:func:`keep_instance` for every instance of a table, ``(N,)`` bool."""
    return _keep(table.bbox_visib, table.px_count_visib, table.visib_fract, min_visible_px, min_visib_fract)


class BopInstanceDataset(Dataset):
    """Crops of ``instances`` (map-style). ``train``: DZI jitter drawn from ``(seed, epoch, index)``
    (:meth:`set_epoch`; the same crop for the same sample in the same epoch, in any worker and
    after a resume); otherwise the centred box."""

    def __init__(
        self,
        instances: Sequence[Instance],
        encoding: PoseEncoding,
        *,
        image_size: int = 224,
        train: bool = False,
        dzi_shift: float = 0.25,
        dzi_scale: float = 0.25,
        dzi_pad: float = 1.5,
        rotation_only: bool = False,
        symmetries: dict[int, torch.Tensor] | None = None,
        seed: int = 0,
    ) -> None:
        self.instances = instances if isinstance(instances, InstanceTable) else list(instances)
        self.seed, self.epoch = int(seed), 0
        #: obj_id → its ``models_info`` symmetry rotations, padded to one size ``(S, 3, 3)`` with a mask
        #: (for the symmetry-aware regression losses; samples then carry ``symmetries`` / ``symmetries_mask``)
        self.symmetries = _pad_symmetries(symmetries) if symmetries else None
        self.encoding = encoding
        self.image_size = int(image_size)
        self.train = train
        self.dzi = {"shift": dzi_shift, "scale": dzi_scale, "pad": dzi_pad}
        self.rotation_only = rotation_only

    def __len__(self) -> int:
        return len(self.instances)

    def set_epoch(self, epoch: int) -> None:
        """The epoch the training jitter is drawn for (``ResumableDataLoader`` sets it every pass)."""
        self.epoch = int(epoch)

    def box(self, inst: Instance, rng: np.random.Generator | None) -> tuple[np.ndarray, float]:
        """The crop ``(centre, side)`` of an instance (its object box; clipped to the image in training)."""
        bbox = clip_box(inst.bbox_obj, inst.image_hw) if self.train else inst.bbox_obj
        return dzi(bbox, inst.image_hw, rng=rng, **self.dzi)

    def __getitem__(self, i: int) -> dict[str, Any]:
        inst = self.instances[i]
        rng = np.random.default_rng([self.seed, self.epoch, int(i)]) if self.train else None
        centre, side = self.box(inst, rng)
        S = self.image_size
        rgb = crop(read_rgb(inst.rgb_path), centre, side, S)
        mask = crop(read_mask(inst.mask_visib_path), centre, side, S, nearest=True)
        image = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).float().div_(255.0)
        mask_t = torch.from_numpy(mask)
        image = image * mask_t
        R = torch.from_numpy(inst.R).float()
        t = torch.from_numpy(inst.t).float()
        K = torch.from_numpy(inst.K).float()
        c = torch.from_numpy(np.asarray(centre)).float()
        s = torch.tensor(float(side))
        R_net, delta = self.encoding.encode(R.double(), t.double(), K.double(), c.double(), s.double(), S)
        if self.rotation_only:
            pose = R_net.float()
        else:
            pose = torch.eye(4)
            pose[:3, :3], pose[:3, 3] = R_net.float(), delta.float()
        return {
            "image": image,
            "mask": mask_t,
            "pose": pose,
            "rotation": R,
            "translation": t,
            "K": K,
            "centre": c,
            "side": s,
            "obj_id": torch.tensor(inst.obj_id),
            "scene_id": torch.tensor(inst.scene_id),
            "im_id": torch.tensor(inst.im_id),
            "gt_idx": torch.tensor(inst.gt_idx),
            "index": torch.tensor(i),
            **(
                {
                    "symmetries": self.symmetries[0][inst.obj_id],
                    "symmetries_mask": self.symmetries[1][inst.obj_id],
                }
                if self.symmetries is not None
                else {}
            ),
        }


def _pad_symmetries(
    sets: dict[int, torch.Tensor],
) -> tuple[dict[int, torch.Tensor], dict[int, torch.Tensor]]:
    """Pad every object's symmetry rotations to the largest set (identity rows, masked out)."""
    size = max(len(v) for v in sets.values())
    rots, masks = {}, {}
    for k, v in sets.items():
        r = torch.eye(3).repeat(size, 1, 1)
        r[: len(v)] = v.float()
        m = torch.zeros(size, dtype=torch.bool)
        m[: len(v)] = True
        rots[int(k)], masks[int(k)] = r, m
    return rots, masks


class BopDataModule(L.LightningDataModule):
    """A BOP dataset (T-LESS by default) for ``posediff fit`` / ``eval``.

    Args:
        root: the dataset folder (``models/``, the split folders, the targets file).
        train_splits: concatenated for training, sampled uniformly over instances (T-LESS: PBR + real).
        test_split: the split of :attr:`targets`.
        targets: the targets file in ``root`` (``null``: every test instance with visib_fract ≥ 0.1).
        models_dir, eval_models_dir: model folders in ``root`` (real T-LESS: ``models_cad``).
        obj_ids: the objects to use (``null``: all in ``models_info.json``).
        image_size: crop size (paper: 224).
        dzi_shift, dzi_scale, dzi_pad: Dynamic Zoom-In (paper / authors: 0.25, 0.25, 1.5).
        augment: a module for training batches (``HardAugment``) or ``null``.
        min_visible_px, min_visib_fract: the instance filter (module docstring).
        rotation: ``allocentric`` | ``egocentric``.
        translation_stats: ``{mean: [3], std: [3]}`` of the raw SITE translation; ``null`` computes
            them from the training split (``posediff fit`` stores them in the checkpoint's config).
        group: ``se3`` / ``r3so3`` (pose ``[R | δ̂]``) or ``so3`` (rotation only).
        max_train_instances: train on at most this many instances (the first, after filtering).
        max_test_instances: score at most this many test targets (the first).
        val_fraction, max_val_images: validation (``val/loss``, which picks ``best.ckpt``) holds out
            this fraction of the training *images* (at most ``max_val_images``, at least one, never
            all), chosen by a permutation seeded by ``seed``: every instance of a held-out image is
            a validation instance (centred crops, no augmentation) and is excluded from training and
            from the translation statistics. The test split is never read for validation.
    """

    def __init__(
        self,
        root: str,
        *,
        train_splits: Sequence[str] = ("train_pbr", "train_primesense"),
        test_split: str = "test_primesense",
        targets: str | None = "test_targets_bop19.json",
        models_dir: str = "models",
        eval_models_dir: str = "models_eval",
        obj_ids: Sequence[int] | None = None,
        image_size: int = 224,
        dzi_shift: float = 0.25,
        dzi_scale: float = 0.25,
        dzi_pad: float = 1.5,
        augment: nn.Module | None = None,
        min_visible_px: int = 64,
        min_visib_fract: float = 0.0,
        rotation: str = "allocentric",
        translation_stats: dict[str, Sequence[float]] | None = None,
        group: LieGroup | str = "se3",
        seed: int = 0,
        batch_size: int = 32,
        num_workers: int = 0,
        max_train_instances: int | None = None,
        max_test_instances: int | None = None,
        val_fraction: float = 0.05,
        max_val_images: int = 100,
    ) -> None:
        super().__init__()
        self.group = get_group(group) if isinstance(group, str) else group
        if self.group.name not in ("so3", "se3", "r3so3"):
            raise ValueError(
                f"BOP poses need a 3-D rotation group (so3, se3, r3so3), not {self.group.name!r}"
            )
        if not 0.0 < float(val_fraction) < 1.0 or int(max_val_images) < 1:
            raise ValueError(
                f"data.val_fraction must be in (0, 1) and data.max_val_images ≥ 1, got {val_fraction}, {max_val_images}"
            )
        self.val_fraction, self.max_val_images = float(val_fraction), int(max_val_images)
        if not root:
            raise ValueError(
                "data.root is not set: point it at a BOP dataset folder (posediff data make-bop out=DIR makes one)"
            )
        self.root = Path(str(root))
        self.train_splits, self.test_split, self.targets_file = list(train_splits), test_split, targets
        self.models = BopModels(self.root, models_dir, eval_models_dir)
        self.obj_ids = None if obj_ids is None else [int(o) for o in obj_ids]
        if self.obj_ids is not None:
            self.models.check(self.obj_ids, "data.obj_ids")
        self.image_size = int(image_size)
        self.dzi = {"dzi_shift": dzi_shift, "dzi_scale": dzi_scale, "dzi_pad": dzi_pad}
        self.augment = augment
        self.min_visible_px, self.min_visib_fract = int(min_visible_px), float(min_visib_fract)
        stats = dict(translation_stats) if translation_stats else {}
        self.encoding = PoseEncoding(rotation, stats.get("mean"), stats.get("std"))
        self.seed, self.batch_size, self.num_workers = int(seed), int(batch_size), int(num_workers)
        self.max_train, self.max_test = max_train_instances, max_test_instances
        self.rotation_only = self.group.matrix_dim == 3
        self.train: BopInstanceDataset | None = None
        #: held-out training images (see ``val_fraction``)
        self.val: BopInstanceDataset | None = None
        self.test: BopInstanceDataset | None = None
        #: test targets dropped by the instance filter (scored as misses)
        self.skipped: list[Instance] = []
        #: all test targets (ground-truth instances the protocol scores)
        self.targets: list[Instance] = []
        #: (scene_id, im_id, obj_id) → the target's ``inst_count`` (BOP19: how many of the
        #: object's top-scored estimates in that image are matched)
        self.inst_count: dict[tuple[int, int, int], int] = {}
        self._targets_read: list[Instance] | None = None
        self.summary: dict[str, Any] = {}

    @property
    def shapes(self) -> list[str]:
        """Object names (``obj_000001`` …), the rows of the per-object tables."""
        return [f"obj_{o:06d}" for o in (self.obj_ids or self.models.obj_ids)]

    def _dataset(self, instances: Sequence[Instance], train: bool) -> BopInstanceDataset:
        return BopInstanceDataset(
            instances,
            self.encoding,
            image_size=self.image_size,
            train=train,
            rotation_only=self.rotation_only,
            symmetries=self.symmetry_rotations(),
            seed=self.seed,
            **self.dzi,
        )

    def symmetry_rotations(self) -> dict[int, torch.Tensor]:
        """obj_id → the rotations of its ``models_info`` symmetries (discretised every 0.01 rad, as the
        BOP toolkit), for the symmetry-aware losses of the regression baselines and the anchor."""
        if getattr(self, "_symmetry_rotations", None) is None:
            ids = self.obj_ids or self.models.obj_ids
            self._symmetry_rotations = {
                int(o): torch.from_numpy(np.asarray(self.models.symmetries(int(o))[0])) for o in ids
            }
        return self._symmetry_rotations

    def _train_instances(self) -> tuple[InstanceTable, InstanceTable]:
        """``(train, val)``: the kept training instances, the held-out images' instances removed."""
        table = InstanceTable.concat(
            [
                BopSplit(self.root, split, self.models, obj_ids=self.obj_ids, require_depth=False).instances
                for split in self.train_splits
            ]
        )
        kept = table.take(keep_mask(table, self.min_visible_px, self.min_visib_fract))
        self.summary["train"] = {"instances": len(table), "kept": len(kept), "splits": self.train_splits}
        if not len(kept):
            raise BopFormatError(
                f"no training instances in {self.root} / {self.train_splits} pass the filter"
            )
        train, val = self.split_validation(kept)
        self.summary["train"]["val_images"] = int(len(np.unique(self._image_keys(val))))
        self.summary["train"]["val"] = len(val)
        return (train[: self.max_train] if self.max_train else train), val

    @staticmethod
    def _image_keys(table: InstanceTable) -> np.ndarray:
        """One key per instance naming its image: ``(scene folder index, im_id)`` as one int64."""
        return table.scene.astype(np.int64) * (1 << 32) + table.im_id.astype(np.int64)

    def split_validation(self, table: InstanceTable) -> tuple[InstanceTable, InstanceTable]:
        """``(train, val)`` of the training instances by whole images (``val_fraction``,
        ``max_val_images``), deterministic in ``seed``; val instances in the permutation's image order
        (so the first validation batches mix scenes and objects)."""
        keys = self._image_keys(table)
        images = np.unique(keys)
        n_val = min(self.max_val_images, max(1, round(self.val_fraction * len(images))), len(images) - 1)
        if n_val < 1:
            raise BopFormatError(
                f"{self.root} / {self.train_splits} has one training image: nothing to hold out for validation"
            )
        held = np.random.default_rng([self.seed, 0x5A1]).permutation(images)[:n_val]
        rank = {int(k): r for r, k in enumerate(held)}
        is_val = np.isin(keys, held)
        val_idx = np.flatnonzero(is_val)
        val_idx = val_idx[np.argsort([rank[int(k)] for k in keys[val_idx]], kind="stable")]
        return table.take(np.flatnonzero(~is_val)), table.take(val_idx)

    def fit_translation_stats(self, instances: InstanceTable, draws: int = 4) -> None:
        """Statistics of the raw SITE translation over the training instances under the training
        crops' DZI jitter (``draws`` crops each, seeded): what the network sees, standardised."""
        rng = np.random.default_rng(self.seed)
        hw = instances.image_hw
        box = clip_boxes(instances.bbox_obj, hw)
        dz = {k.removeprefix("dzi_"): v for k, v in self.dzi.items()}
        raws = []
        T = torch.from_numpy
        for _ in range(draws):
            centre, side = dzi_many(box, hw, rng, **dz)
            raws.append(
                PoseEncoding.raw_translation(
                    T(instances.t.astype(np.float64)),
                    T(instances.K.astype(np.float64)),
                    T(centre),
                    T(side),
                    self.image_size,
                )
            )
        self.encoding.fit_stats(torch.cat(raws))

    def read_targets(self) -> list[Instance]:
        """Read the test split's ground truth the BOP19 protocol scores — :attr:`targets`,
        :attr:`inst_count`, :attr:`skipped` — without making any dataset (no translation statistics
        needed; ``posediff score`` uses it). Returns :attr:`targets`."""
        if self._targets_read is None:
            self._targets_read = self._read_test_targets()
        return self.targets

    def _test_instances(self) -> list[Instance]:
        self.read_targets()
        assert self._targets_read is not None
        return self._targets_read

    def _read_test_targets(self) -> list[Instance]:
        split = self.root / self.test_split
        if self.targets_file:
            path = self.root / self.targets_file
            targets = [t for t in read_targets(path) if self.obj_ids is None or t.obj_id in self.obj_ids]
            self.models.check({t.obj_id for t in targets}, str(path))
            images = {(t.scene_id, t.im_id) for t in targets}
            all_inst = BopSplit(self.root, self.test_split, self.models, obj_ids=self.obj_ids, images=images)
            found = {(i.scene_id, i.im_id) for i in all_inst.instances}
            missing = sorted(images - found)
            if missing:
                raise BopFormatError(f"{path} names images {missing[:3]}… that {split} does not have")
            self.targets = target_instances(all_inst.instances, targets)
            self.inst_count = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets}
        else:
            all_inst = BopSplit(self.root, self.test_split, self.models, obj_ids=self.obj_ids)
            self.targets = [i for i in all_inst.instances if i.visib_fract >= 0.1]
            self.inst_count = {}
            for i in self.targets:
                key = (i.scene_id, i.im_id, i.obj_id)
                self.inst_count[key] = self.inst_count.get(key, 0) + 1
        if self.max_test:
            self.targets = self.targets[: self.max_test]
        keep = [keep_instance(i, self.min_visible_px, 0.0) for i in self.targets]
        kept = [i for i, k in zip(self.targets, keep, strict=True) if k]
        self.skipped = [i for i, k in zip(self.targets, keep, strict=True) if not k]
        self.summary["test"] = {"targets": len(self.targets), "kept": len(kept), "skipped": len(self.skipped)}
        return kept

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train is None:
            train, val = self._train_instances()
            if not self.encoding.fitted:  # training instances only: never the held-out ones
                self.fit_translation_stats(train)
            self.train = self._dataset(train, train=True)
            self.val = self._dataset(val, train=False)
        if stage in (None, "fit", "validate", "test", "predict") and self.test is None:
            if not self.encoding.fitted:
                raise BopFormatError(
                    "the translation statistics are unknown: evaluate a checkpoint made by posediff fit "
                    "(it stores them) or set data.translation_stats={mean: [...], std: [...]}"
                )
            self.test = self._dataset(self._test_instances(), train=False)

    # ------------------------------------------------------------------ posediff.data.PoseDataModule
    #: the BOP19 protocol scores the test split (posediff.evaluation.bop)
    scorer: ClassVar[str] = "bop"
    #: a prediction needs a test target's box, mask and camera (``predict index=N``, never ``image=``)
    needs_test_target: ClassVar[bool] = True

    def describe(self) -> str:
        return self.summary_line()

    def checkpoint_data(self) -> dict[str, Any]:
        """The translation statistics of the training split: eval decodes with them."""
        return {"translation_stats": self.encoding.stats()} if self.encoding.fitted else {}

    def results_filename(self, tag: str = "") -> str:
        """The BOP toolkit's ``METHOD_DATASET-SPLIT.csv``: ``posediff[-tag]_<folder>-<split>.csv``."""
        dataset = self.root.name.replace("_", "")
        split = self.test_split.split("_")[0]
        return "posediff" + (f"-{tag.replace('_', '-')}" if tag else "") + f"_{dataset}-{split}.csv"

    @classmethod
    def image_camera(cls, data_config: Any) -> tuple[Any, Any]:
        return None, None

    def prediction_input(self, index: int) -> dict[str, Any]:
        """Test target ``index`` (loader order): its crop, the decoding of network poses to the camera
        frame (mm), the crop's intrinsics, the model, the truth and its symmetric equivalents."""
        import math

        from .roi import crop_intrinsics

        if self.test is None:
            self.setup("test")
        assert self.test is not None
        n = len(self.test)
        if not 0 <= int(index) < n:
            raise IndexError(f"index={index} but the test split has {n} targets with visible pixels")
        sample, inst = self.test[int(index)], self.test.instances[int(index)]
        S, enc = self.image_size, self.encoding
        K, c, s = sample["K"].double(), sample["centre"].double(), sample["side"].double()

        def decode(x: Tensor) -> tuple[Tensor, Tensor]:
            lead = x.shape[:-2]  # rotation-only models are decoded at the true translation
            t = sample["translation"].double().expand(*lead, 3)
            return enc.decode_pose(
                x, K.expand(*lead, 3, 3), c.expand(*lead, 2), s.expand(*lead), S, translation=t
            )

        gt = torch.eye(4, dtype=torch.float64)
        gt[:3, :3], gt[:3, 3] = sample["rotation"].double(), sample["translation"].double()
        syms_R, _ = self.models.symmetries(inst.obj_id, max_sym_disc_step=math.pi / 36, evaluation=True)
        return {
            "image": sample["image"],
            "decode": decode,
            "K": crop_intrinsics(inst.K, c.numpy(), float(s), S),
            "mesh": self.models.mesh(inst.obj_id),
            "gt_pose": gt,
            "gt_rotations": gt[:3, :3].numpy() @ syms_R,
            "mode_translation_radius": 0.1 * self.models.diameter(inst.obj_id),
            "title": f"obj {inst.obj_id} in scene {inst.scene_id} image {inst.im_id}",
            "info": {"scene_id": inst.scene_id, "im_id": inst.im_id, "gt_idx": inst.gt_idx, "obj_id": inst.obj_id,
                     "frame": "camera (OpenCV), translation in mm"},
        }  # fmt: skip

    def summary_line(self) -> str:
        """What was read and what the filter dropped, in one line (``posediff fit`` / ``eval`` print it)."""
        parts = [f"BOP data {self.root}"]
        if "train" in self.summary:
            t = self.summary["train"]
            parts.append(f"train {'+'.join(t['splits'])}: {t['kept']} of {t['instances']} instances kept")
            if "val" in t:
                parts.append(f"validation: {t['val']} of them held out ({t['val_images']} training images)")
        if "test" in self.summary:
            t = self.summary["test"]
            parts.append(
                f"{self.test_split}: {t['targets']} targets, {t['skipped']} skipped "
                f"(≤ {self.min_visible_px} visible pixels; scored as misses)"
            )
        return "; ".join(parts)

    def on_after_batch_transfer(self, batch: dict[str, Tensor], dataloader_idx: int) -> dict[str, Tensor]:
        """Augment training crops on the device, then mask them to the visible pixels again."""
        if self.augment is not None and self.trainer is not None and self.trainer.training:
            batch["image"] = self.augment(batch["image"]) * batch["mask"][:, None]
        return batch

    def train_dataloader(self) -> DataLoader:
        """Shuffled training crops; resumes mid-epoch exactly (:class:`~posediff.data.resumable.ResumableDataLoader`)."""
        assert self.train is not None, "call setup() first"
        return ResumableDataLoader(
            self.train,
            batch_size=self.batch_size,
            shuffle=True,
            seed=self.seed,
            drop_last=len(self.train) >= self.batch_size,
            num_workers=self.num_workers,
            persistent_workers=False,
        )

    def val_dataloader(self) -> DataLoader:
        """The held-out training images (``val_fraction``); never the test split."""
        assert self.val is not None, "call setup('fit') first"
        return eval_loader(self.val, batch_size=self.batch_size, num_workers=self.num_workers)

    def test_dataloader(self) -> DataLoader:
        assert self.test is not None, "call setup() first"
        return eval_loader(self.test, batch_size=self.batch_size, num_workers=self.num_workers)


__all__ = ["BopDataModule", "BopInstanceDataset", "keep_instance"]
