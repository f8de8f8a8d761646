"""Numerics of SO(3) (log at and near π, Haar sampling), the coefficient functions of
``posediff.lie._numerics``, and float32 accuracy of the SE(3) translation at tiny angles."""

import math

import mpmath  # installed with torch (torch → sympy → mpmath); used as an exact oracle
import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

from posediff.lie import SE3, SO3
from posediff.lie._numerics import SMALL_THETA2, Angle, series
from posediff.testing import tangents_at_angles

F64 = torch.float64
F32 = torch.float32
NAMES = "ABCDEF"
EPS64 = torch.finfo(F64).eps


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------ log at exactly π
def _exact_pi_rotations(dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Rotations by exactly π: the three coordinate-axis ones and 2aaᵀ − I for random unit a
    (built in float64, then cast). Returns (R, axes)."""
    axes = torch.eye(3, dtype=F64)
    a = torch.randn(13, 3, generator=_gen(0), dtype=F64)
    a = torch.cat([axes, a / a.norm(dim=-1, keepdim=True)])
    R = 2.0 * a[:, :, None] * a[:, None, :] - torch.eye(3, dtype=F64)
    # the axis ones are exactly diag(1,-1,-1), diag(-1,1,-1), diag(-1,-1,1)
    assert torch.equal(R[:3], torch.diag_embed(2.0 * axes - 1.0))
    return R.to(dtype), a.to(dtype)


@pytest.mark.parametrize("dtype, tol", [(F64, 1e-12), (F32, 1e-6)], ids=["float64", "float32"])
def test_log_at_exactly_pi(dtype: torch.dtype, tol: float) -> None:
    R, a = _exact_pi_rotations(dtype)
    phi = SO3().log(R)
    assert phi.dtype == dtype
    assert torch.isfinite(phi).all()
    assert_close(SO3().exp(phi), R, atol=tol, rtol=0.0)
    assert_close(phi.norm(dim=-1), torch.full((R.shape[0],), math.pi, dtype=dtype), atol=tol, rtol=0.0)
    # the vector is ±π a (either sign is a valid principal log at π)
    sign = torch.sign((phi * a).sum(-1, keepdim=True))
    assert_close(phi, sign * math.pi * a, atol=4 * tol, rtol=0.0)


def test_log_just_below_pi_keeps_digits() -> None:
    v = tangents_at_angles(SO3(), [math.pi - 1e-7] * 32, seed=1)
    R = SO3().exp(v)
    # oracle for R: the matrix exponential of the skew matrix (independent of exp_so3)
    assert_close(R, torch.linalg.matrix_exp(SO3().hat(v)), atol=1e-13, rtol=0.0)
    assert_close(SO3().log(R), v, atol=1e-9, rtol=0.0)


# ------------------------------------------------------------------------------ _numerics
def _closed_torch(name: str, theta2: Tensor) -> Tensor:
    """The textbook closed forms, evaluated directly in float64."""
    th = theta2.sqrt()
    s, c = torch.sin(th), torch.cos(th)
    return {
        "A": lambda: s / th,
        "B": lambda: (1.0 - c) / theta2,
        "C": lambda: (th - s) / th**3,
        "D": lambda: (1.0 - 0.5 * th * torch.cos(0.5 * th) / torch.sin(0.5 * th)) / theta2,
        "E": lambda: (theta2 + 2.0 * c - 2.0) / (2.0 * theta2**2),
        "F": lambda: (2.0 * th - 3.0 * s + th * c) / (2.0 * th**5),
    }[name]()


def _cancellation(name: str, theta2: Tensor) -> Tensor:
    """Condition number of the closed form's numerator: Σ|terms| / |numerator|. The direct
    float64 closed forms lose this factor of digits (≈ 5 for C, ≈ 50 for E, ≈ 5000 for F at θ = ½)."""
    th = theta2.sqrt()
    s, c = torch.sin(th), torch.cos(th)
    half = 0.5 * th
    terms, num = {
        "A": (s, s),
        "B": (1.0 + c, 1.0 - c),
        "C": (th + s, th - s),
        "D": (1.0 + half * torch.cos(half) / torch.sin(half), 1.0 - half * torch.cos(half) / torch.sin(half)),
        "E": (theta2 + 2.0 * c.abs() + 2.0, theta2 + 2.0 * c - 2.0),
        "F": (2.0 * th + 3.0 * s.abs() + th * c.abs(), 2.0 * th - 3.0 * s + th * c),
    }[name]
    return terms / num.abs()


def _closed_mpmath(name: str, theta2: float) -> float:
    """The closed forms at ≥ 40 significant digits (plus what their cancellation loses at small θ),
    rounded to float64: an exact oracle."""
    lost = 3 * max(0, -math.floor(math.log10(theta2))) if theta2 > 0 else 0
    with mpmath.workdps(40 + lost):
        t2 = mpmath.mpf(theta2)
        th = mpmath.sqrt(t2)
        s, c = mpmath.sin(th), mpmath.cos(th)
        value = {
            "A": lambda: s / th,
            "B": lambda: (1 - c) / t2,
            "C": lambda: (th - s) / th**3,
            "D": lambda: (1 - (th / 2) * mpmath.cot(th / 2)) / t2,
            "E": lambda: (t2 + 2 * c - 2) / (2 * t2**2),
            "F": lambda: (2 * th - 3 * s + th * c) / (2 * th**5),
        }[name]()
        return float(value)


def _assert_rel_close(actual: Tensor, expected: Tensor, rtol: Tensor, what: str) -> None:
    """``assert_close`` with an elementwise relative tolerance: the error measured in units of the
    allowed error must be within 1."""
    scaled = (actual - expected) / (expected.abs() * rtol)
    assert_close(scaled, torch.zeros_like(scaled), atol=1.0, rtol=0.0, msg=lambda m: f"{what}: {m}")


def _around_threshold() -> Tensor:
    x = SMALL_THETA2
    below = [math.nextafter(x, 0.0), x * (1 - 1e-12), x * (1 - 1e-6), x * (1 - 1e-3)]
    above = [x, math.nextafter(x, 1.0), x * (1 + 1e-12), x * (1 + 1e-6), x * (1 + 1e-3)]
    return torch.tensor(below + above, dtype=F64)


@pytest.mark.parametrize("name", NAMES)
def test_series_matches_closed_form_at_threshold(name: str) -> None:
    """At θ² just below and just above SMALL_THETA2 the Taylor series (truncated as the code
    truncates it) equals the closed form to 1e-14 relative — against the exact closed form, and
    against the direct float64 closed form up to that form's own cancellation error."""
    t2 = _around_threshold()
    ser = series(name, t2)
    exact = torch.tensor([_closed_mpmath(name, float(x)) for x in t2], dtype=F64)
    assert_close(ser, exact, atol=0.0, rtol=1e-14)
    direct = _closed_torch(name, t2)
    # elementwise relative error allowed: 1e-14, or 8 ulp times the cancellation factor if larger
    allowed = torch.clamp(8 * EPS64 * _cancellation(name, t2), min=1e-14)
    _assert_rel_close(ser, direct, allowed, f"{name}: series vs direct float64 closed form")


@pytest.mark.parametrize("name", NAMES)
def test_angle_is_continuous_across_threshold(name: str) -> None:
    below = torch.tensor([math.nextafter(SMALL_THETA2, 0.0)] * 2, dtype=F64)
    at = torch.tensor([SMALL_THETA2, math.nextafter(SMALL_THETA2, 1.0)], dtype=F64)
    assert bool(Angle(below).small.all()) and not bool(Angle(at).small.any())  # really two branches
    lo, hi = getattr(Angle(below), name)(), getattr(Angle(at), name)()
    allowed = max(1e-14, 8 * EPS64 * float(_cancellation(name, at).max()))
    assert_close(hi, lo, atol=0.0, rtol=allowed)
    # and each side is the true value: the series to 1e-14, the closed form to its cancellation
    for x, val, rtol in ((below, lo, 1e-14), (at, hi, allowed)):
        exact = torch.tensor([_closed_mpmath(name, float(v)) for v in x], dtype=F64)
        assert_close(val, exact, atol=0.0, rtol=rtol)


@pytest.mark.parametrize("name", NAMES)
def test_angle_matches_exact_values_over_the_range(name: str) -> None:
    """Both branches of Angle against the high-precision oracle from θ² = 1e-20 to θ = 3.

    (Closer to π, A = sin θ/θ is ill-conditioned in θ itself — the rounding of θ = √θ² alone
    moves it by ~θ/|sin θ| ulp — so a relative bound there would test the oracle, not the code.)"""
    t2 = torch.cat([
        torch.logspace(-20, math.log10(SMALL_THETA2) - 1e-9, 25, dtype=F64),
        torch.linspace(math.sqrt(SMALL_THETA2), 3.0, 25, dtype=F64) ** 2,
    ])  # fmt: skip
    got = getattr(Angle(t2), name)()
    exact = torch.tensor([_closed_mpmath(name, float(x)) for x in t2], dtype=F64)
    allowed = torch.clamp(8 * EPS64 * _cancellation(name, t2), min=1e-14)
    allowed = torch.where(Angle(t2).small, torch.full_like(allowed, 1e-14), allowed)
    _assert_rel_close(got, exact, allowed, f"{name}: Angle vs exact")


def test_angle_at_zero_gives_series_constants() -> None:
    ang = Angle(torch.zeros(3, dtype=F64))
    expected = {"A": 1.0, "B": 1 / 2, "C": 1 / 6, "D": 1 / 12, "E": 1 / 24, "F": 1 / 120}
    for name, value in expected.items():
        got = getattr(ang, name)()
        assert torch.isfinite(got).all(), name
        assert_close(got, torch.full((3,), value, dtype=F64), atol=0.0, rtol=1e-15, msg=name)
    # and in float32, with finite gradients through θ² = 0
    t2 = torch.zeros(2, dtype=F32, requires_grad=True)
    total = sum(getattr(Angle(t2), n)().sum() for n in NAMES)
    (grad,) = torch.autograd.grad(total, t2)
    assert torch.isfinite(grad).all()


# ------------------------------------------------------------------------------ Haar sampling
def test_sample_uniform_is_haar() -> None:
    n = 20000
    R = SO3().sample_uniform((n,), generator=_gen(2), dtype=F64)
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta, _ = torch.acos(cos).sort()
    cdf = (theta - torch.sin(theta)) / math.pi
    i = torch.arange(1, n + 1, dtype=F64)
    ks = float(torch.maximum(i / n - cdf, cdf - (i - 1) / n).max())
    assert ks < 0.02, f"Kolmogorov–Smirnov statistic {ks:.4f} against (θ − sin θ)/π"
    mean = R.mean(0)
    assert_close(mean, torch.zeros(3, 3, dtype=F64), atol=0.03, rtol=0.0)
    # a sanity check that the statistic has power: angles uniform on [0, π] are far off
    bad = torch.linspace(0.0, math.pi, n, dtype=F64)
    bad_cdf = (bad - torch.sin(bad)) / math.pi
    assert float(torch.maximum(i / n - bad_cdf, bad_cdf - (i - 1) / n).max()) > 0.1


# ------------------------------------------------------------------------------ SE3 float32
def test_se3_float32_translation_at_tiny_angles() -> None:
    """Headline requirement: float32 SE3 exp translation within 1e-6 of float64 for θ ∈ [1e-8, 1e-3]."""
    angles = [10.0**k for k in range(-8, -2)] * 16
    xi = tangents_at_angles(SE3(), angles, seed=3)
    xi[:, :3] = (
        xi[:, :3]
        / xi[:, :3].norm(dim=-1, keepdim=True)
        * (0.5 + torch.rand(len(angles), 1, generator=_gen(4), dtype=F64))
    )  # |ρ| in [0.5, 1.5]
    xi32 = xi.to(F32)
    t32 = SE3().exp(xi32)[:, :3, 3]
    assert t32.dtype == F32
    # float64 reference on exactly the float32 inputs, so only the kernel's error is measured
    ref = torch.linalg.matrix_exp(SE3().hat(xi32.to(F64)))[:, :3, 3]
    assert_close(SE3().exp(xi32.to(F64))[:, :3, 3], ref, atol=1e-14, rtol=0.0)
    err = float((t32.to(F64) - ref).abs().max())
    assert err <= 1e-6, f"float32 SE3 translation error {err:.2e} > 1e-6"
