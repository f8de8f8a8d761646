"""SYMSOL and SYMSOL-T rendered locally and headless: shapes and symmetries, the renderer,
sharded datasets (atomic, resumable) and the Lightning DataModule."""

from .datamodule import SymsolDataModule, SymsolRenderDataset, SymsolShardDataset
from .poses import DATASETS, VARIANTS, PoseSet, sample_poses
from .render import (
    FOV_DEG,
    SCENE_DISTANCE,
    SCENE_VERSION,
    Look,
    Rendered,
    SymsolRenderer,
    intrinsics,
    prepare_gl,
)
from .shapes import (
    SHAPE_IDS,
    SHAPE_SIZE,
    Symmetry,
    authors_frame,
    equivalent_poses,
    make_mesh,
    shape_name,
    symmetries,
)
from .shards import RenderSummary, SymsolShards, render_dataset

__all__ = [
    "DATASETS",
    "FOV_DEG",
    "SCENE_DISTANCE",
    "SCENE_VERSION",
    "Look",
    "SHAPE_IDS",
    "SHAPE_SIZE",
    "VARIANTS",
    "PoseSet",
    "RenderSummary",
    "Rendered",
    "Symmetry",
    "SymsolDataModule",
    "SymsolRenderDataset",
    "SymsolRenderer",
    "SymsolShardDataset",
    "SymsolShards",
    "authors_frame",
    "equivalent_poses",
    "intrinsics",
    "make_mesh",
    "prepare_gl",
    "render_dataset",
    "sample_poses",
    "shape_name",
    "symmetries",
]
