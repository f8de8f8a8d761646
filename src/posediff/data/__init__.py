"""Datasets and Lightning DataModules: the symmetric-shape toy (no images), SYMSOL / SYMSOL-T
(:mod:`.symsol`) and BOP datasets (:mod:`.bop`), each speaking :class:`PoseDataModule` (:mod:`.protocol`)."""

from .protocol import LoaderPredictions as LoaderPredictions
from .protocol import PoseDataModule as PoseDataModule
from .toy import SymmetryToy as SymmetryToy
from .toy import SymmetryToyDataModule as SymmetryToyDataModule

__all__ = ["LoaderPredictions", "PoseDataModule", "SymmetryToy", "SymmetryToyDataModule"]
