"""Object symmetries, one part for the whole package: the exact groups of the SYMSOL shapes and
symmetry-aware rotation distances (:mod:`.groups`), and :class:`SymmetrySet` — the symmetries of any
object as a value, from a SYMSOL shape or a BOP ``models_info`` entry (:mod:`.sets`). Data and
metrics both import it; it imports only :mod:`posediff.lie`."""

from .groups import (
    GENERATORS_DOC,
    GOLDEN_RATIO,
    SHAPES,
    STANDARD_EMBEDDING_SPREAD,
    canonical_rotation,
    decode_embedding,
    embedding_dim,
    embedding_statistics,
    equivalent_rotations,
    invariant_embedding,
    is_continuous,
    min_angle_to_equivalents,
    num_modes,
    rotation_angle,
    set_chordal_sq,
    shape_name,
    standardise_embedding,
    symmetric_chordal_sq,
    symmetry_group,
    symsol_chordal_sq,
    unstandardise_embedding,
)
from .sets import SymmetrySet, as_symmetry_set, min_angle_deg

__all__ = [
    "GENERATORS_DOC",
    "GOLDEN_RATIO",
    "SHAPES",
    "STANDARD_EMBEDDING_SPREAD",
    "SymmetrySet",
    "as_symmetry_set",
    "canonical_rotation",
    "decode_embedding",
    "embedding_dim",
    "embedding_statistics",
    "equivalent_rotations",
    "invariant_embedding",
    "standardise_embedding",
    "unstandardise_embedding",
    "is_continuous",
    "min_angle_deg",
    "min_angle_to_equivalents",
    "num_modes",
    "rotation_angle",
    "set_chordal_sq",
    "shape_name",
    "symmetric_chordal_sq",
    "symmetry_group",
    "symsol_chordal_sq",
]
