"""Reusable contract checks for posediff's pluggable families (importable by out-of-tree code)."""

from .diffusion import KERNEL_CHECKS as KERNEL_CHECKS
from .diffusion import SAMPLER_CHECKS as SAMPLER_CHECKS
from .diffusion import SCHEDULE_CHECKS as SCHEDULE_CHECKS
from .diffusion import SCORE_TARGET_CHECKS as SCORE_TARGET_CHECKS
from .diffusion import kernel_contract as kernel_contract
from .diffusion import sampler_contract as sampler_contract
from .diffusion import schedule_contract as schedule_contract
from .diffusion import score_target_contract as score_target_contract
from .lie import LIE_GROUP_CHECKS as LIE_GROUP_CHECKS
from .lie import lie_group_contract as lie_group_contract
from .lie import oracle_jacobians as oracle_jacobians
from .lie import tangents_at_angles as tangents_at_angles
from .models import POSE_MODEL_CHECKS as POSE_MODEL_CHECKS
from .models import pose_model_contract as pose_model_contract
from .models import synthetic_batch as synthetic_batch

__all__ = [
    "KERNEL_CHECKS",
    "SAMPLER_CHECKS",
    "SCHEDULE_CHECKS",
    "SCORE_TARGET_CHECKS",
    "kernel_contract",
    "sampler_contract",
    "schedule_contract",
    "score_target_contract",
    "LIE_GROUP_CHECKS",
    "lie_group_contract",
    "oracle_jacobians",
    "tangents_at_angles",
    "POSE_MODEL_CHECKS",
    "pose_model_contract",
    "synthetic_batch",
]
