"""The symmetric-shape toy: learn the full set of equivalent poses from a symmetry-invariant condition.

No images: the condition of a sample is a vector

    [one-hot shape (5)] ⊕ [canonical rotation, flattened (9)] ⊕ [translation (3), groups with one]

where the canonical rotation is the equivalent pose closest to the identity
(:func:`posediff.symmetry.canonical_rotation`) — the same for every pose that looks identical. The
target distribution given the condition is therefore uniform over the equivalent poses
``{(R·S, t)}``: 12 / 24 / 60 of them for tet / cube / icosa, a circle (cone) or two (cylinder) for
the continuous shapes. On SE(3) and R³×SO(3) the network must also recover the translation.

Training poses are ``R ~ Haar``, ``t ~ U[−b, b]³``; because R is Haar-uniform, R given its
canonical representative is uniform over the equivalent set, which is exactly the target.

``num_poses = M`` restricts the orientations to M fixed canonical poses per shape (chosen from
``pose_seed``, shared by the train and test splits, and spread out: farthest-point selection among
random candidates under the symmetry-aware distance, so that no two conditions are a few degrees
apart — two poses 13° apart modulo the symmetries, as plain random draws gave, are learned as one
condition with satellite modes 13° off): a training rotation is ``R_m · S`` with S a
uniformly random symmetry (and ``Rz(α)``/flip for cone and cylinder), so the target is still the
full equivalent set, but the network has M conditions per shape to learn instead of a continuum.
The CPU toy uses it (the continuum needs far more training than minutes; see docs/sampling.md).
"""

import math
from collections.abc import Sequence
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from ..lie import LieGroup, get_group
from ..lie.so3 import uniform_rotation
from ..symmetry import SHAPES, canonical_rotation, is_continuous, min_angle_to_equivalents, symmetry_group
from .protocol import LoaderPredictions
from .resumable import ResumableDataLoader, eval_loader

#: seed offsets of the toy's held-out draws (the training set is drawn from ``seed`` itself)
TEST_SEED_OFFSET = 1_000_003
VAL_SEED_OFFSET = 2_000_003


class SymmetryToy(Dataset[dict[str, Tensor]]):
    """``size`` toy samples drawn once from ``seed`` (vectorised), as a map-style dataset.

    Items: ``cond (C,)`` float32, ``pose (n, n)`` the group element, ``rotation (3, 3)``,
    ``translation (3,)`` (zeros without translation), ``shape`` (index into ``posediff.symmetry.SHAPES``,
    as SYMSOL's).
    """

    def __init__(
        self,
        group: LieGroup | str,
        size: int,
        *,
        shapes: Sequence[str] = SHAPES,
        seed: int = 0,
        translation_bound: float = 1.0,
        per_shape: bool = False,
        num_poses: int | None = None,
        pose_seed: int = 12345,
    ) -> None:
        self.group = get_group(group) if isinstance(group, str) else group
        unknown = [s for s in shapes if s not in SHAPES]
        if unknown:
            raise ValueError(f"unknown shape(s) {unknown}; available: {', '.join(SHAPES)}")
        self.shapes = tuple(shapes)
        self.has_translation = self.group.name in ("se3", "r3so3")
        if self.group.name not in ("so3", "se3", "r3so3"):
            raise ValueError(f"the toy needs a 3-D rotation group (so3, se3, r3so3), not {self.group.name!r}")
        gen = torch.Generator().manual_seed(int(seed))
        n = int(size)
        if per_shape:  # `size` samples of every shape, in shape order
            shape_idx = torch.arange(len(self.shapes)).repeat_interleave(n)
        else:
            shape_idx = torch.randint(0, len(self.shapes), (n,), generator=gen)
        total = shape_idx.numel()
        if num_poses:
            rot = _rotations_from_pose_set(
                self.shapes, shape_idx, int(num_poses), int(pose_seed), gen, per_shape
            )
        else:
            rot = uniform_rotation((total,), gen, torch.device("cpu"), torch.float64)
        trans = (torch.rand(total, 3, generator=gen, dtype=torch.float64) * 2 - 1) * translation_bound
        if not self.has_translation:
            trans.zero_()
        canon = torch.empty_like(rot)
        for k, shape in enumerate(self.shapes):
            sel = shape_idx == k
            if sel.any():
                canon[sel] = canonical_rotation(shape, rot[sel])
        global_idx = torch.tensor([SHAPES.index(s) for s in self.shapes])[shape_idx]
        onehot = torch.nn.functional.one_hot(global_idx, len(SHAPES)).to(torch.float64)
        parts = [onehot, canon.reshape(total, 9)] + ([trans] if self.has_translation else [])
        self.cond = torch.cat(parts, dim=-1).float()
        self.rotation = rot.float()
        self.translation = trans.float()
        self.shape = global_idx
        if self.group.matrix_dim == 3:
            self.pose = self.rotation
        else:
            pose = torch.eye(4).repeat(total, 1, 1)
            pose[:, :3, :3] = self.rotation
            pose[:, :3, 3] = self.translation
            self.pose = pose

    @property
    def cond_dim(self) -> int:
        return int(self.cond.shape[-1])

    def __len__(self) -> int:
        return int(self.cond.shape[0])

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {
            "cond": self.cond[i],
            "pose": self.pose[i],
            "rotation": self.rotation[i],
            "translation": self.translation[i],
            "shape": self.shape[i],
        }


def _rotations_from_pose_set(
    shapes: Sequence[str],
    shape_idx: Tensor,
    num_poses: int,
    pose_seed: int,
    gen: torch.Generator,
    cycle: bool,
) -> Tensor:
    """``R_m · S``: one of ``num_poses`` fixed poses of the sample's shape times a random symmetry."""
    base = torch.stack([spread_poses(shape, num_poses, pose_seed) for shape in shapes])
    total = shape_idx.numel()
    if cycle:  # test split: go through the poses in order
        m = torch.cat([torch.arange((shape_idx == k).sum()) % num_poses for k in range(len(shapes))])
    else:
        m = torch.randint(0, num_poses, (total,), generator=gen)
    out = torch.empty(total, 3, 3, dtype=torch.float64)
    for k, shape in enumerate(shapes):
        sel = shape_idx == k
        n = int(sel.sum())
        if n == 0:
            continue
        if is_continuous(shape):
            alpha = torch.rand(n, generator=gen, dtype=torch.float64) * 2 * math.pi
            c, s_ = alpha.cos(), alpha.sin()
            sym = torch.zeros(n, 3, 3, dtype=torch.float64)
            sym[:, 0, 0], sym[:, 0, 1], sym[:, 1, 0], sym[:, 1, 1], sym[:, 2, 2] = c, -s_, s_, c, 1.0
            if shape == "cyl":
                flip = torch.rand(n, generator=gen) < 0.5
                sym[flip] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)) @ sym[flip]
        else:
            group = symmetry_group(shape)
            sym = group[torch.randint(0, len(group), (n,), generator=gen)]
        out[sel] = base[k, m[sel]] @ sym
    return out


def spread_poses(shape: str, num_poses: int, seed: int, candidates_per_pose: int = 32) -> Tensor:
    """``num_poses`` canonical rotations of ``shape``, far apart modulo its symmetries, ``(M, 3, 3)`` float64.

    Greedy farthest-point selection among ``candidates_per_pose · M`` Haar-random candidates drawn
    from ``seed``, with the distance ``min_S ∠(R_i, R_j S)``
    (:func:`posediff.symmetry.min_angle_to_equivalents`); deterministic given the seed.
    """
    gen = torch.Generator().manual_seed(int(seed))
    cand = uniform_rotation((max(int(num_poses) * candidates_per_pose, 1),), gen, "cpu", torch.float64)
    chosen = [0]
    dist = min_angle_to_equivalents(shape, cand, cand[0])
    for _ in range(int(num_poses) - 1):
        nxt = int(dist.argmax())
        chosen.append(nxt)
        dist = torch.minimum(dist, min_angle_to_equivalents(shape, cand, cand[nxt]))
    return torch.stack([canonical_rotation(shape, cand[i]) for i in chosen])


class SymmetryToyDataModule(LoaderPredictions, L.LightningDataModule):
    """Train / validation / test splits of the toy (three separately seeded draws), for
    ``posediff fit +experiment=toy_*``. Validation (``val/loss``, which picks ``best.ckpt``) never
    reads the test draw. The training loader resumes mid-epoch exactly
    (:class:`~posediff.data.resumable.ResumableDataLoader`).

    Args:
        group: the pose group (so3, se3 or r3so3).
        shapes: which shapes (default all five).
        num_train: training samples (drawn once; an epoch is one pass).
        num_test_per_shape: evaluation conditions per shape.
        num_val_per_shape: validation samples per shape (seed ``seed + VAL_SEED_OFFSET``).
        batch_size: conditions per training step (each gets ``num_noisy`` noisy poses in the model).
        num_poses: fixed canonical poses per shape (None: every orientation; see ``SymmetryToy``).
    """

    def __init__(
        self,
        group: LieGroup | str,
        *,
        shapes: Sequence[str] = SHAPES,
        num_train: int = 100_000,
        num_test_per_shape: int = 8,
        num_val_per_shape: int = 8,
        batch_size: int = 32,
        seed: int = 0,
        translation_bound: float = 1.0,
        num_workers: int = 0,
        num_poses: int | None = None,
    ) -> None:
        super().__init__()
        self.group = get_group(group) if isinstance(group, str) else group
        self.shapes = tuple(shapes)
        self.num_train = int(num_train)
        self.num_test_per_shape = int(num_test_per_shape)
        self.num_val_per_shape = int(num_val_per_shape)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.translation_bound = float(translation_bound)
        self.num_workers = int(num_workers)
        self.num_poses = num_poses
        self.train: SymmetryToy | None = None
        self.val: SymmetryToy | None = None
        self.test: SymmetryToy | None = None

    def setup(self, stage: str | None = None) -> None:
        kw: dict[str, Any] = {
            "shapes": self.shapes,
            "translation_bound": self.translation_bound,
            "num_poses": self.num_poses,
        }
        if stage in (None, "fit") and self.train is None:
            self.train = SymmetryToy(self.group, self.num_train, seed=self.seed, **kw)
        if stage in (None, "fit", "validate") and self.val is None:
            self.val = SymmetryToy(
                self.group, self.num_val_per_shape, seed=self.seed + VAL_SEED_OFFSET, per_shape=True, **kw
            )
        if self.test is None:
            self.test = SymmetryToy(
                self.group, self.num_test_per_shape, seed=self.seed + TEST_SEED_OFFSET, per_shape=True, **kw
            )

    @property
    def cond_dim(self) -> int:
        return len(SHAPES) + 9 + (3 if self.group.name in ("se3", "r3so3") else 0)

    def train_dataloader(self) -> DataLoader:
        assert self.train is not None
        return ResumableDataLoader(
            self.train,
            batch_size=self.batch_size,
            shuffle=True,
            seed=self.seed,
            drop_last=True,
            num_workers=self.num_workers,
        )

    def val_dataloader(self) -> DataLoader:
        """The separately seeded validation draw (never the test draw)."""
        assert self.val is not None, "call setup('fit') first"
        return eval_loader(self.val, batch_size=self.batch_size)

    def test_dataloader(self) -> DataLoader:
        assert self.test is not None
        return eval_loader(self.test, batch_size=self.num_test_per_shape)

    # ------------------------------------------------------------------ posediff.data.PoseDataModule
    def describe(self) -> str:
        return f"symmetry toy: shapes {', '.join(self.shapes)}, {self.num_test_per_shape} test conditions per shape"

    def prediction_input(self, index: int) -> dict[str, Any]:
        raise ValueError("the symmetry toy has no images to predict from (its condition is the shape alone)")
