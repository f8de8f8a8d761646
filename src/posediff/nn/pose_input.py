"""What the denoiser sees of a pose: its tangent vector ``Log X`` (paper §4.4) or the entries of its
matrix (the 3×3 rotation, plus the translation column for 4×4 groups — smooth everywhere, no
re-wrapping of the rotation vector at θ = π; beyond the paper)."""

from typing import Any

from torch import Tensor

#: the choices of ``module.pose_input``
POSE_INPUTS = ("tangent", "matrix")


def pose_input_dim(group: Any, pose_input: str) -> int:
    """Width of the denoiser's pose input for a group (class or instance): the tangent dimension, or
    3·n for an n×n matrix."""
    if pose_input == "tangent":
        return int(group.dim)
    if pose_input == "matrix":
        return 3 * int(group.matrix_dim)
    raise ValueError(f"unknown pose_input {pose_input!r}; choose one of: {', '.join(POSE_INPUTS)}")


def pose_features(group: Any, x: Tensor, pose_input: str) -> Tensor:
    """What the denoiser sees of poses ``x (..., n, n)``: ``(..., pose_input_dim)``."""
    if pose_input == "matrix":
        return x[..., :3, :].flatten(-2)
    return group.log(x)


__all__ = ["POSE_INPUTS", "pose_features", "pose_input_dim"]
