"""The benchmarks' own files, read safely: the official SYMSOL I / II (:mod:`.symsol`: the unpacked
``symsol_dataset.zip`` or a prepared TensorFlow Datasets folder, :mod:`.tfrecord` without TensorFlow)
and the paper authors' SYMSOL-T (:mod:`.symsolt`, its ``annotations.gz`` through :mod:`.unpickle`,
which runs nothing)."""

from .base import OfficialDataError, OfficialDataModule, padded_symmetries
from .symsol import (
    SymsolOfficialDataModule,
    SymsolOfficialDataset,
    decode_png,
    find_tfds_folder,
)
from .symsolt import SymsoltOfficialDataModule, model_frame, quaternion_wxyz_to_matrix, to_posediff, to_theirs
from .tfrecord import TFRecordError, TFRecordFile, encode_example, parse_example, write_tfrecord
from .unpickle import PlainUnpickler, UnsafePickleError, load_plain_pickle

__all__ = [
    "OfficialDataError",
    "OfficialDataModule",
    "PlainUnpickler",
    "SymsolOfficialDataModule",
    "SymsolOfficialDataset",
    "SymsoltOfficialDataModule",
    "TFRecordError",
    "TFRecordFile",
    "UnsafePickleError",
    "decode_png",
    "encode_example",
    "find_tfds_folder",
    "load_plain_pickle",
    "model_frame",
    "padded_symmetries",
    "parse_example",
    "quaternion_wxyz_to_matrix",
    "to_posediff",
    "to_theirs",
    "write_tfrecord",
]
