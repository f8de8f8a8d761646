"""Reusable contract checks for posediff's pluggable families (importable by out-of-tree code)."""

from .lie import LIE_GROUP_CHECKS as LIE_GROUP_CHECKS
from .lie import lie_group_contract as lie_group_contract
from .lie import oracle_jacobians as oracle_jacobians
from .lie import tangents_at_angles as tangents_at_angles

__all__ = ["LIE_GROUP_CHECKS", "lie_group_contract", "oracle_jacobians", "tangents_at_angles"]
