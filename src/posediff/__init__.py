"""posediff: 6D object pose as a distribution, by score-based diffusion on Lie groups.

Implements Hsiao et al., "Confronting Ambiguity in 6D Object Pose Estimation via Score-Based
Diffusion on SE(3)" (CVPR 2024).
"""

from .lie import R3SO3 as R3SO3
from .lie import SE2 as SE2
from .lie import SE3 as SE3
from .lie import SO3 as SO3
from .lie import LieGroup as LieGroup
from .lie import get_group as get_group

try:  # the one place the version is written is pyproject.toml
    from importlib.metadata import PackageNotFoundError as _NotFound
    from importlib.metadata import version as _version

    __version__ = _version("posediff")
except _NotFound:  # pragma: no cover - a source tree that was never installed
    __version__ = "0+unknown"

#: the rest of the public API, imported on first use (``posediff.load_checkpoint`` does not pay for
#: Lightning or the data modules until it is called)
_LAZY = {
    "load_checkpoint": ("posediff.models", "load_checkpoint"),
    "predict": ("posediff.evaluation.predict", "predict"),
    "Prediction": ("posediff.evaluation.predict", "Prediction"),
    "load_image": ("posediff.evaluation.predict", "load_image"),
    "PoseDiffusionModule": ("posediff.models", "PoseDiffusionModule"),
    "PoseRegressionModule": ("posediff.models", "PoseRegressionModule"),
    "SymmetrySet": ("posediff.symmetry", "SymmetrySet"),
    "modes": ("posediff.diffusion", "modes"),
}


def __getattr__(name: str):  # noqa: ANN202 - PEP 562
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'posediff' has no attribute {name!r}")


__all__ = ["LieGroup", "SO3", "R3SO3", "SE3", "SE2", "get_group", "__version__", *_LAZY]
