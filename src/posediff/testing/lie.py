"""The Lie group contract: checks every ``LieGroup`` must pass, against float64 oracles.

Use it on your own group::

    from posediff.testing import lie_group_contract
    lie_group_contract(MyGroup())            # raises AssertionError naming every failed check

or one check at a time (``LIE_GROUP_CHECKS`` maps names to functions ``check(group, device)``),
which is how ``tests/contracts/test_lie_group.py`` parametrizes over the registry.

Oracles are independent of the group's own code where possible: ``torch.linalg.matrix_exp`` of
the algebra representation for Exp and the Jacobians (through autograd), conjugation of the
matrix representation for the adjoint, and central finite differences.
"""

import math
from collections.abc import Callable

import torch
from torch import Tensor
from torch.testing import assert_close

from ..lie.base import LieGroup

F64 = torch.float64
F32 = torch.float32

#: rotation angles (rad) at which the checks probe every group
SMALL_ANGLES = (0.0, 1e-12, 1e-8, 1e-6, 1e-4, 1e-2)
NEAR_PI_ANGLES = (math.pi - 1e-3, math.pi - 1e-5, math.pi - 1e-7)
BATCH_SHAPES: tuple[tuple[int, ...], ...] = ((), (1,), (3, 1, 2))

Check = Callable[[LieGroup, torch.device], None]


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def tangents_at_angles(
    group: LieGroup,
    angles: Tensor | list[float] | tuple[float, ...],
    *,
    seed: int = 0,
    dtype: torch.dtype = F64,
    device: torch.device | str = "cpu",
    trans_scale: float = 1.0,
) -> Tensor:
    """Tangent vectors ``(n, dim)`` whose rotation part has the given norms (random axes) and
    whose other components are Gaussian with std ``trans_scale``."""
    g = _gen(seed)
    angles = torch.as_tensor(angles, dtype=F64)
    n = angles.numel()
    xi = torch.randn(n, group.dim, generator=g, dtype=F64) * trans_scale
    rs = group.rotation_slice
    k = len(range(group.dim)[rs])
    axis = torch.randn(n, k, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    xi[:, rs] = axis * angles.reshape(n, 1)
    return xi.to(device=device, dtype=dtype)


def generic_angles(n: int, seed: int = 1, low: float = 0.05, high: float = 3.0) -> list[float]:
    u = torch.rand(n, generator=_gen(seed), dtype=F64)
    return (low + (high - low) * u).tolist()


def _valid(group: LieGroup, g: Tensor, what: str, atol: float | None = None) -> None:
    try:
        group.check(g, atol=atol)
    except ValueError as e:
        raise AssertionError(f"{what}: {e}") from None


# ---------------------------------------------------------------------------------- checks
def check_shapes_dtype_device(group: LieGroup, device: torch.device) -> None:
    """Outputs have the documented shapes, broadcast over batch dims, keep dtype and device."""
    n, d, p = group.matrix_dim, group.dim, group.point_dim
    for dtype in (F32, F64):
        for shape in BATCH_SHAPES:
            xi = torch.randn(*shape, d, dtype=dtype, device=device, generator=None) * 0.5
            g = group.exp(xi)
            pts = torch.randn(*shape, p, dtype=dtype, device=device)
            outs = {
                "exp": (g, (*shape, n, n)),
                "log": (group.log(g), (*shape, d)),
                "compose": (group.compose(g, g), (*shape, n, n)),
                "inverse": (group.inverse(g), (*shape, n, n)),
                "act": (group.act(g, pts), (*shape, p)),
                "hat": (group.hat(xi), (*shape, n, n)),
                "vee": (group.vee(group.hat(xi)), (*shape, d)),
                "adjoint": (group.adjoint(g), (*shape, d, d)),
                "jac_left": (group.jac_left(xi), (*shape, d, d)),
                "jac_right": (group.jac_right(xi), (*shape, d, d)),
                "jac_left_inv": (group.jac_left_inv(xi), (*shape, d, d)),
                "jac_right_inv": (group.jac_right_inv(xi), (*shape, d, d)),
                "rplus": (group.rplus(g, xi), (*shape, n, n)),
                "rminus": (group.rminus(g, g), (*shape, d)),
                "project": (group.project(g), (*shape, n, n)),
                "identity": (group.identity(shape, dtype=dtype, device=device), (*shape, n, n)),
                "sample_uniform": (group.sample_uniform(shape, dtype=dtype, device=device), (*shape, n, n)),
            }
            for op, (out, expected) in outs.items():
                assert tuple(out.shape) == expected, f"{op}: shape {tuple(out.shape)} != {expected} ({dtype})"
                assert out.dtype == dtype, f"{op}: dtype {out.dtype} != {dtype}"
                assert out.device.type == torch.device(device).type, f"{op}: device {out.device}"
    # broadcasting across batch dims
    a = group.exp(torch.randn(2, 1, d, dtype=F64, device=device))
    b = group.exp(torch.randn(1, 3, d, dtype=F64, device=device))
    assert tuple(group.compose(a, b).shape) == (2, 3, n, n), "compose does not broadcast (2,1) with (1,3)"
    assert tuple(group.rminus(a, b).shape) == (2, 3, d), "rminus does not broadcast"
    assert tuple(group.rplus(a, torch.zeros(3, d, dtype=F64, device=device)).shape) == (2, 3, n, n)
    assert tuple(group.act(a, torch.zeros(5, 1, 3, p, dtype=F64, device=device)).shape) == (5, 2, 3, p)
    assert tuple(group.identity(4).shape) == (4, n, n)


def check_bad_input(group: LieGroup, device: torch.device) -> None:
    """A wrong trailing shape raises ``ValueError`` naming the expected shape."""
    n, d = group.matrix_dim, group.dim
    bad_tangent = torch.zeros(2, d + 1, dtype=F64, device=device)
    bad_element = torch.zeros(2, n + 1, n + 1, dtype=F64, device=device)
    tangent_ops = ["exp", "hat", "jac_left", "jac_right", "jac_left_inv", "jac_right_inv"]
    element_ops = ["log", "inverse", "adjoint", "project", "check"]
    calls: list[tuple[str, Callable[[], object], str]] = []
    calls += [(op, lambda op=op: getattr(group, op)(bad_tangent), f"(*batch, {d})") for op in tangent_ops]
    calls += [
        (op, lambda op=op: getattr(group, op)(bad_element), f"(*batch, {n}, {n})") for op in element_ops
    ]
    good = group.identity((2,), dtype=F64, device=device)
    calls += [
        ("compose", lambda: group.compose(good, bad_element), f"(*batch, {n}, {n})"),
        ("rplus", lambda: group.rplus(good, bad_tangent), f"(*batch, {d})"),
        (
            "act",
            lambda: group.act(good, torch.zeros(2, group.point_dim + 1, dtype=F64)),
            f"{group.point_dim})",
        ),
    ]
    for op, call, expected in calls:
        try:
            call()
        except ValueError as e:
            msg = str(e)
            assert expected in msg and "\n" not in msg, f"{op}: unhelpful error {msg!r}"
        else:
            raise AssertionError(f"{op}: accepted a wrongly shaped input")


def check_no_in_place(group: LieGroup, device: torch.device) -> None:
    """No operation writes into its inputs."""
    xi = tangents_at_angles(group, generic_angles(4), device=device)
    g = group.exp(xi)
    h = group.sample_uniform((4,), generator=_gen(3), dtype=F64, device=device)
    pts = torch.randn(4, group.point_dim, dtype=F64, device=device)
    before = [t.clone() for t in (xi, g, h, pts)]
    for out in (
        group.exp(xi),
        group.log(g),
        group.compose(g, h),
        group.inverse(g),
        group.act(g, pts),
        group.adjoint(g),
        group.jac_left(xi),
        group.jac_right(xi),
        group.jac_left_inv(xi),
        group.jac_right_inv(xi),
        group.rplus(g, xi),
        group.rminus(g, h),
        group.project(g),
        group.hat(xi),
        group.vee(group.hat(xi)),
    ):
        out.add_(1.0)  # a returned view of an input would show up below
    for a, b in zip(before, (xi, g, h, pts), strict=True):
        assert torch.equal(a, b), "an operation modified its input or returned a view of it"


def check_exp_matches_matrix_exp(group: LieGroup, device: torch.device) -> None:
    """``matrix_rep(exp(ξ)) == matrix_exp(algebra_rep(ξ))`` to 1e-12 in float64."""
    angles = list(SMALL_ANGLES) + generic_angles(24) + list(NEAR_PI_ANGLES) + [math.pi, 4.0, 6.0]
    xi = tangents_at_angles(group, angles, device=device)
    expected = torch.linalg.matrix_exp(group.algebra_rep(xi))
    assert_close(group.matrix_rep(group.exp(xi)), expected, atol=1e-12, rtol=0.0)
    assert_close(group.vee(group.hat(xi)), xi, atol=0.0, rtol=0.0)


def check_log_exp_roundtrip(group: LieGroup, device: torch.device) -> None:
    """``log(exp(ξ)) == ξ`` for rotation angles < π, including π − 1e-7."""
    angles = list(SMALL_ANGLES) + generic_angles(24) + list(NEAR_PI_ANGLES)
    xi = tangents_at_angles(group, angles, device=device)
    assert_close(group.log(group.exp(xi)), xi, atol=1e-10, rtol=1e-10)


def check_exp_log_roundtrip(group: LieGroup, device: torch.device) -> None:
    """``exp(log(g)) == g`` everywhere: random elements, identity, and rotations of π and π − 1e-7."""
    g = [
        group.sample_uniform((64,), generator=_gen(5), dtype=F64, device=device),
        group.identity((1,), dtype=F64, device=device),
        group.exp(tangents_at_angles(group, [math.pi] * 4 + list(NEAR_PI_ANGLES), device=device)),
        group.exp(tangents_at_angles(group, SMALL_ANGLES, device=device)),
    ]
    for x in g:
        assert_close(group.exp(group.log(x)), x, atol=1e-12, rtol=0.0)
        phi = group.log(x)[..., group.rotation_slice]
        assert float(phi.norm(dim=-1).max()) <= math.pi + 1e-12, "log is not principal (angle > π)"


def check_group_axioms(group: LieGroup, device: torch.device) -> None:
    """Identity, inverse, associativity, closure; ``compose`` is the matmul of ``matrix_rep``."""
    a, b, c = (group.sample_uniform((16,), generator=_gen(s), dtype=F64, device=device) for s in (10, 11, 12))
    e = group.identity((16,), dtype=F64, device=device)
    assert_close(group.compose(a, e), a, atol=1e-14, rtol=0.0)
    assert_close(group.compose(e, a), a, atol=1e-14, rtol=0.0)
    assert_close(group.compose(a, group.inverse(a)), e, atol=1e-13, rtol=0.0)
    assert_close(group.compose(group.inverse(a), a), e, atol=1e-13, rtol=0.0)
    assert_close(
        group.compose(group.compose(a, b), c), group.compose(a, group.compose(b, c)), atol=1e-12, rtol=0.0
    )
    assert_close(
        group.matrix_rep(group.compose(a, b)), group.matrix_rep(a) @ group.matrix_rep(b), atol=1e-13, rtol=0.0
    )
    assert_close(
        group.matrix_rep(group.inverse(a)), torch.linalg.inv(group.matrix_rep(a)), atol=1e-12, rtol=0.0
    )
    for x in (a, group.compose(a, b), group.inverse(c)):
        _valid(group, x, "closure")
    # act applies the element as a (homogeneous) matrix to points: R p (+ t)
    p = torch.randn(16, group.point_dim, dtype=F64, device=device)
    k = group.point_dim
    if group.matrix_dim == k:
        expected = (a @ p.unsqueeze(-1)).squeeze(-1)
    elif group.matrix_dim == k + 1:
        expected = (a[..., :k, :k] @ p.unsqueeze(-1)).squeeze(-1) + a[..., :k, k]
    else:  # a group of another layout tests its own action
        expected = group.act(a, p)
    assert_close(group.act(a, p), expected, atol=1e-14, rtol=0.0)
    assert_close(group.act(e, p), p, atol=1e-15, rtol=0.0)


def check_rplus_rminus(group: LieGroup, device: torch.device) -> None:
    """``rminus(g, rplus(g, ξ)) == ξ`` and ``rplus(g, rminus(g, h)) == h``."""
    g = group.sample_uniform((32,), generator=_gen(20), dtype=F64, device=device)
    h = group.sample_uniform((32,), generator=_gen(21), dtype=F64, device=device)
    xi = tangents_at_angles(group, generic_angles(32, seed=22), device=device)
    assert_close(group.rplus(g, xi), group.compose(g, group.exp(xi)), atol=1e-13, rtol=0.0)
    assert_close(group.rminus(g, group.rplus(g, xi)), xi, atol=1e-10, rtol=1e-10)
    assert_close(group.rplus(g, group.rminus(g, h)), h, atol=1e-12, rtol=0.0)
    assert_close(group.rminus(g, h), group.log(group.compose(group.inverse(g), h)), atol=1e-11, rtol=0.0)


def check_adjoint(group: LieGroup, device: torch.device) -> None:
    """``algebra_rep(Ad(g) ξ) == M(g) algebra_rep(ξ) M(g)⁻¹`` and ``g Exp(ξ) g⁻¹ = Exp(Ad(g) ξ)``."""
    g = group.sample_uniform((16,), generator=_gen(30), dtype=F64, device=device)
    xi = tangents_at_angles(group, generic_angles(16, seed=31), device=device)
    ad_xi = (group.adjoint(g) @ xi.unsqueeze(-1)).squeeze(-1)
    M = group.matrix_rep(g)
    assert_close(
        group.algebra_rep(ad_xi), M @ group.algebra_rep(xi) @ torch.linalg.inv(M), atol=1e-12, rtol=0.0
    )
    conj = group.compose(group.compose(g, group.exp(xi)), group.inverse(g))
    assert_close(group.exp(ad_xi), conj, atol=1e-12, rtol=0.0)


def _algebra_coordinates(group: LieGroup, X: Tensor) -> Tensor:
    """Coordinates of ``X`` (in the algebra representation) in the basis ``algebra_rep(e_i)``."""
    basis = group.algebra_rep(torch.eye(group.dim, dtype=X.dtype, device=X.device))
    B = basis.reshape(group.dim, -1).T  # (m², d)
    flat = X.reshape(*X.shape[:-2], -1, 1)
    return torch.linalg.lstsq(B.expand(*flat.shape[:-2], *B.shape), flat).solution.squeeze(-1)


def oracle_jacobians(group: LieGroup, xi: Tensor) -> tuple[Tensor, Tensor]:
    """(J_r, J_l) at each row of ``xi`` from autograd through ``matrix_exp`` (float64)."""
    jr, jl = [], []
    for x in xi:

        def f(v: Tensor) -> Tensor:
            return torch.linalg.matrix_exp(group.algebra_rep(v))

        M = f(x)
        dM = torch.autograd.functional.jacobian(f, x)  # (m, m, d)
        dM = dM.movedim(-1, 0)  # (d, m, m)
        Minv = torch.linalg.inv(M)
        jr.append(_algebra_coordinates(group, Minv @ dM).T)  # column j = J_r e_j
        jl.append(_algebra_coordinates(group, dM @ Minv).T)
    return torch.stack(jr), torch.stack(jl)


def check_jacobians_autograd(group: LieGroup, device: torch.device) -> None:
    """``jac_right``/``jac_left`` equal the autograd derivative of ``matrix_exp`` (float64)."""
    angles = [0.0, 1e-6, 0.3] + generic_angles(6, seed=40) + [math.pi - 1e-3]
    xi = tangents_at_angles(group, angles, device=device)
    jr, jl = oracle_jacobians(group, xi.cpu())
    assert_close(group.jac_right(xi).cpu(), jr, atol=1e-10, rtol=0.0)
    assert_close(group.jac_left(xi).cpu(), jl, atol=1e-10, rtol=0.0)


def check_jacobians_finite_differences(group: LieGroup, device: torch.device) -> None:
    """Central differences of ``rminus(exp(ξ), exp(ξ ± h e_j))`` reproduce J_r (and J_l via Ad)."""
    xi = tangents_at_angles(group, [0.0, 1e-3] + generic_angles(6, seed=41), device=device)
    h = 1e-6
    eye = torch.eye(group.dim, dtype=F64, device=device)
    g = group.exp(xi).unsqueeze(1)  # (n, 1, m, m)
    plus = group.exp(xi.unsqueeze(1) + h * eye)
    minus = group.exp(xi.unsqueeze(1) - h * eye)
    jr_fd = ((group.rminus(g, plus) - group.rminus(g, minus)) / (2 * h)).mT
    assert_close(group.jac_right(xi), jr_fd, atol=1e-7, rtol=0.0)
    ginv = group.inverse(group.exp(xi)).unsqueeze(1)
    jl_fd = ((group.log(group.compose(plus, ginv)) - group.log(group.compose(minus, ginv))) / (2 * h)).mT
    assert_close(group.jac_left(xi), jl_fd, atol=1e-7, rtol=0.0)


def check_jacobian_identities(group: LieGroup, device: torch.device) -> None:
    """Inverses are inverses, ``J_l(z) z = z = J_r(z) z``, ``J_l(z) = J_r(−z)``, ``J_l = Ad(Exp z) J_r``."""
    xi = tangents_at_angles(
        group, list(SMALL_ANGLES) + generic_angles(12, seed=42) + [math.pi], device=device
    )
    eye = torch.eye(group.dim, dtype=F64, device=device).expand(xi.shape[0], -1, -1)
    jl, jr = group.jac_left(xi), group.jac_right(xi)
    assert_close(jl @ group.jac_left_inv(xi), eye, atol=1e-11, rtol=0.0)
    assert_close(jr @ group.jac_right_inv(xi), eye, atol=1e-11, rtol=0.0)
    assert_close((jl @ xi.unsqueeze(-1)).squeeze(-1), xi, atol=1e-12, rtol=0.0)
    assert_close((jr @ xi.unsqueeze(-1)).squeeze(-1), xi, atol=1e-12, rtol=0.0)
    assert_close(group.jac_left(-xi), jr, atol=1e-14, rtol=0.0)
    assert_close(jl, group.adjoint(group.exp(xi)) @ jr, atol=1e-11, rtol=0.0)


def check_gradcheck(group: LieGroup, device: torch.device) -> None:
    """``torch.autograd.gradcheck`` passes for exp, log and compose in float64."""
    xi = tangents_at_angles(group, [1e-9, 1e-4, 0.7, 2.0, math.pi - 1e-2], device=device)
    g = group.exp(xi).detach()
    h = group.sample_uniform((5,), generator=_gen(50), dtype=F64, device=device)

    def _ok(fn: Callable[..., Tensor], *inputs: Tensor, what: str) -> None:
        ins = tuple(t.detach().clone().requires_grad_(True) for t in inputs)
        assert torch.autograd.gradcheck(fn, ins, eps=1e-6, atol=1e-6, rtol=1e-5), what

    _ok(group.exp, xi, what="exp")
    _ok(group.log, g, what="log")
    _ok(group.compose, g, h, what="compose")
    _ok(group.rplus, h, xi, what="rplus")


def check_finite_gradients(group: LieGroup, device: torch.device) -> None:
    """Gradients of exp, log, compose, rplus, rminus are finite at θ = 0 and θ → π (and at π)."""
    for dtype in (F64, F32):
        for angle in (0.0, 1e-7, math.pi - 1e-6, math.pi):
            xi = tangents_at_angles(group, [angle] * 3, dtype=dtype, device=device)
            if angle == 0.0:
                xi = torch.zeros_like(xi)
            g = group.exp(xi).detach()
            h = group.sample_uniform((3,), generator=_gen(60), dtype=dtype, device=device)
            cases: dict[str, tuple[Callable[..., Tensor], tuple[Tensor, ...]]] = {
                "exp": (group.exp, (xi,)),
                "log": (group.log, (g,)),
                "compose": (group.compose, (g, h)),
                "rplus": (group.rplus, (h, xi)),
                "rminus": (group.rminus, (h, g)),
                "jac_right_inv": (group.jac_right_inv, (xi,)),
            }
            for op, (fn, args) in cases.items():
                ins = [a.detach().clone().requires_grad_(True) for a in args]
                out = fn(*ins)
                assert torch.isfinite(out).all(), f"{op}: non-finite value at angle {angle} ({dtype})"
                weights = torch.randn(out.shape, generator=_gen(61), dtype=F64).to(out)
                grads = torch.autograd.grad((out * weights).sum(), ins)
                for gr in grads:
                    assert torch.isfinite(gr).all(), f"{op}: non-finite gradient at angle {angle} ({dtype})"


def check_float32_stability(group: LieGroup, device: torch.device) -> None:
    """float32 exp/log agree with float64 to ~1e-6 at tiny angles (1e-8…1e-3) and near π."""
    tiny = [1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3]
    xi64 = tangents_at_angles(group, tiny * 4 + generic_angles(8, seed=70), device=device)
    exp32 = group.exp(xi64.to(F32))
    err = (exp32.to(F64) - group.exp(xi64)).abs().max()
    assert err <= 1e-6, f"float32 exp error {float(err):.2e} > 1e-6"
    g64 = group.exp(xi64)
    g32 = g64.to(F32)
    log32 = group.log(g32)
    err = (log32.to(F64) - group.log(g64)).abs().max()
    assert err <= 2e-6, f"float32 log error {float(err):.2e} > 2e-6"
    # near π the sign of the axis is ambiguous in float32: compare exp(log(g)) instead
    near = group.exp(tangents_at_angles(group, [math.pi - 1e-3, math.pi - 1e-6, math.pi] * 3, device=device))
    near32 = near.to(F32)
    err = (group.exp(group.log(near32)) - near32).abs().max()
    assert err <= 2e-6, f"float32 exp(log(g)) error near π {float(err):.2e} > 2e-6"
    assert torch.isfinite(group.jac_right_inv(xi64.to(F32))).all()


def check_sample_uniform(group: LieGroup, device: torch.device) -> None:
    """Samples are valid elements, reproducible with a generator, translations inside the box."""
    a = group.sample_uniform((256,), generator=_gen(80), dtype=F64, device=device, bound=2.0)
    b = group.sample_uniform((256,), generator=_gen(80), dtype=F64, device=device, bound=2.0)
    assert torch.equal(a, b), "sample_uniform is not reproducible with the same generator"
    _valid(group, a, "sample_uniform")
    xi = group.log(a)
    trans = [i for i in range(group.dim) if i not in range(group.dim)[group.rotation_slice]]
    n = group.matrix_dim
    if trans:
        t = a[..., : n - 1, n - 1]
        assert float(t.abs().max()) <= 2.0, "translation outside [-bound, bound]"
        assert float(t.abs().max()) > 1.0, "translation does not fill the box"
    assert float(xi[..., group.rotation_slice].norm(dim=-1).max()) > 2.0, "rotations are not spread out"


def check_project(group: LieGroup, device: torch.device) -> None:
    """``project`` fixes valid elements and maps perturbed matrices to valid ones."""
    g = group.sample_uniform((32,), generator=_gen(90), dtype=F64, device=device)
    assert_close(group.project(g), g, atol=1e-12, rtol=0.0)
    noisy = g + 1e-3 * torch.randn(g.shape, generator=_gen(91), dtype=F64).to(g)
    _valid(group, group.project(noisy), "project")
    assert float((group.project(noisy) - g).abs().max()) < 1e-2
    try:
        group.check(noisy)
    except ValueError:
        pass
    else:
        raise AssertionError("check accepted a perturbed (invalid) element")


LIE_GROUP_CHECKS: dict[str, Check] = {
    "shapes_dtype_device": check_shapes_dtype_device,
    "bad_input": check_bad_input,
    "no_in_place": check_no_in_place,
    "exp_matches_matrix_exp": check_exp_matches_matrix_exp,
    "log_exp_roundtrip": check_log_exp_roundtrip,
    "exp_log_roundtrip": check_exp_log_roundtrip,
    "group_axioms": check_group_axioms,
    "rplus_rminus": check_rplus_rminus,
    "adjoint": check_adjoint,
    "jacobians_autograd": check_jacobians_autograd,
    "jacobians_finite_differences": check_jacobians_finite_differences,
    "jacobian_identities": check_jacobian_identities,
    "gradcheck": check_gradcheck,
    "finite_gradients": check_finite_gradients,
    "float32_stability": check_float32_stability,
    "sample_uniform": check_sample_uniform,
    "project": check_project,
}


def lie_group_contract(
    group: LieGroup, *, device: torch.device | str = "cpu", checks: list[str] | None = None
) -> list[str]:
    """Run the contract on ``group``; return the names of the checks run.

    Raises ``AssertionError`` listing every failed check with its message.
    """
    names = list(LIE_GROUP_CHECKS) if checks is None else checks
    unknown = sorted(set(names) - set(LIE_GROUP_CHECKS))
    if unknown:
        raise KeyError(f"unknown checks {unknown}; available: {', '.join(LIE_GROUP_CHECKS)}")
    dev = torch.device(device)
    failures = []
    for name in names:
        try:
            LIE_GROUP_CHECKS[name](group, dev)
        except AssertionError as e:
            failures.append(f"{name}: {str(e).strip().splitlines()[0] if str(e).strip() else 'failed'}")
    if failures:
        raise AssertionError(
            f"{group!r} fails {len(failures)} contract check(s):\n  " + "\n  ".join(failures)
        )
    return names
