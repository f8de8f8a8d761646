"""``LieGroup(compiled=True)`` runs the same kernels through torch.compile: same numbers."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.lie import SE3, LieGroup
from posediff.testing import tangents_at_angles

ANGLES = [0.0, 1e-7, 1e-3, 0.5, 2.0, math.pi - 1e-6, math.pi]


def _compare(group_cls: type[LieGroup], ops: tuple[str, ...], dtype: torch.dtype) -> None:
    eager, fused = group_cls(), group_cls(compiled=True)
    xi = tangents_at_angles(eager, ANGLES * 5, dtype=dtype)
    g = eager.exp(xi)
    h = eager.sample_uniform((xi.shape[0],), generator=torch.Generator().manual_seed(0), dtype=dtype)
    args = {"exp": (xi,), "log": (g,), "compose": (g, h), "rminus": (g, h), "rplus": (h, xi)}
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    for op in ops:
        assert_close(getattr(fused, op)(*args[op]), getattr(eager, op)(*args[op]), atol=tol, rtol=0.0)


def test_compiled_se3_matches_eager_float32() -> None:
    _compare(SE3, ("exp", "log"), torch.float32)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LieGroup.registry))
def test_compiled_matches_eager(name: str) -> None:
    _compare(LieGroup.registry[name], ("exp", "log", "compose", "rminus", "rplus"), torch.float64)


def test_compiled_group_under_autograd_uses_eager_kernels() -> None:
    """With inputs that require grad a compiled group differentiates like the eager one."""
    xi = tangents_at_angles(SE3(), ANGLES, dtype=torch.float64).requires_grad_(True)
    grads = []
    for group in (SE3(), SE3(compiled=True)):
        (gr,) = torch.autograd.grad(group.log(group.exp(xi)).square().sum(), xi)
        grads.append(gr)
    assert_close(grads[1], grads[0], atol=1e-10, rtol=0.0)
