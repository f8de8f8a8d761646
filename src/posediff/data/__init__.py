"""Datasets and Lightning DataModules: the symmetric-shape toy (no images); SYMSOL and T-LESS later."""

from .toy import SymmetryToy as SymmetryToy
from .toy import SymmetryToyDataModule as SymmetryToyDataModule

__all__ = ["SymmetryToy", "SymmetryToyDataModule"]
