"""``LieGroup(compiled=True)`` runs the same kernels through torch.compile: same numbers."""

import math

import pytest
import torch
from torch.testing import assert_close

from posediff.lie import SE3, SO3, LieGroup
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


def test_compiled_group_under_autograd_matches_eager() -> None:
    """Under autograd a compiled group runs its compiled kernels and compiled backward, with the
    eager group's gradients (first order, retained graphs) and second derivatives."""
    xi = tangents_at_angles(SE3(), ANGLES, dtype=torch.float64).requires_grad_(True)
    grads, hessians = [], []
    for group in (SE3(), SE3(compiled=True)):
        loss = group.log(group.exp(xi)).square().sum()
        (gr,) = torch.autograd.grad(loss, xi, retain_graph=True)
        (again,) = torch.autograd.grad(loss, xi)
        assert_close(again, gr, atol=0.0, rtol=0.0)
        grads.append(gr)
        (first,) = torch.autograd.grad(group.exp(xi).sin().sum(), xi, create_graph=True)
        (second,) = torch.autograd.grad(first.sum(), xi)
        hessians.append(second)
    assert_close(grads[1], grads[0], atol=1e-10, rtol=0.0)
    # log∘exp is the identity below π (at π the principal log jumps)
    assert_close(grads[0][:-2], 2.0 * xi.detach()[:-2], atol=1e-8, rtol=0.0)
    assert_close(hessians[1], hessians[0], atol=1e-10, rtol=0.0)


def test_compiled_backward_is_the_compiled_vjp(monkeypatch: pytest.MonkeyPatch) -> None:
    """A first derivative goes through the compiled vector-Jacobian product, not the eager graph."""
    from posediff.lie import base

    calls: list[str] = []
    real = base._compiled_vjp

    def spy(cls: type, op: str):  # type: ignore[no-untyped-def]
        calls.append(op)
        return real(cls, op)

    monkeypatch.setattr(base, "_compiled_vjp", spy)
    xi = tangents_at_angles(SO3(), ANGLES, dtype=torch.float64).requires_grad_(True)
    h = SO3().exp(tangents_at_angles(SO3(), ANGLES[::-1], dtype=torch.float64))
    group = SO3(compiled=True)
    out = group.compose(group.exp(xi), h)
    (gr,) = torch.autograd.grad(out.sum(), xi)
    assert calls == ["compose", "exp"]
    xe = xi.detach().requires_grad_(True)
    (ge,) = torch.autograd.grad(SO3().compose(SO3().exp(xe), h).sum(), xe)
    assert_close(gr, ge, atol=1e-12, rtol=0.0)
    assert torch.isfinite(gr).all()


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LieGroup.registry))
def test_compiled_gradients_match_eager(name: str) -> None:
    cls = LieGroup.registry[name]
    eager, fused = cls(), cls(compiled=True)
    xi0 = tangents_at_angles(eager, ANGLES * 3, dtype=torch.float64)
    h = eager.sample_uniform((xi0.shape[0],), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for op in ("exp", "log", "compose", "rplus", "rminus"):
        grads = []
        for group in (eager, fused):
            xi = xi0.clone().requires_grad_(True)
            g = eager.exp(xi)  # eager on both sides: only `op` differs
            args = {"exp": (xi,), "log": (g,), "compose": (g, h), "rminus": (g, h), "rplus": (h, xi)}[op]
            (gr,) = torch.autograd.grad(getattr(group, op)(*args).sin().sum(), xi)
            grads.append(gr)
        assert torch.isfinite(grads[1]).all(), op
        assert_close(grads[1], grads[0], atol=1e-9, rtol=0.0, msg=lambda m, op=op: f"{name}.{op}: {m}")
