"""The Lie group contract, run over every registered group: a new subclass is tested automatically."""

import pytest
import torch

from posediff.lie import LieGroup
from posediff.testing import LIE_GROUP_CHECKS, lie_group_contract

GROUPS = sorted(LieGroup.registry)


@pytest.mark.parametrize("check", list(LIE_GROUP_CHECKS))
@pytest.mark.parametrize("name", GROUPS)
def test_contract(name: str, check: str, device: torch.device) -> None:
    LIE_GROUP_CHECKS[check](LieGroup.registry[name](), device)


def test_contract_covers_the_builtin_groups() -> None:
    assert {"so3", "r3so3", "se3", "se2"} <= set(GROUPS)


def test_contract_reports_a_broken_group() -> None:
    """The importable suite fails loudly on a group with a wrong Exp (it can fail)."""
    from posediff.lie import SO3

    class WrongSO3(SO3):  # no name: not registered
        @classmethod
        def _exp(cls, xi: torch.Tensor) -> torch.Tensor:
            return super()._exp(1.001 * xi)

    with pytest.raises(AssertionError, match="exp_matches_matrix_exp"):
        lie_group_contract(WrongSO3(), checks=["exp_matches_matrix_exp", "bad_input"])


def test_contract_rejects_unknown_check_names() -> None:
    from posediff.lie import SO3

    with pytest.raises(KeyError, match="unknown checks"):
        lie_group_contract(SO3(), checks=["nope"])
