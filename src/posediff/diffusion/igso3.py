"""The isotropic Gaussian on SO(3), ``IG_SO(3)`` (paper supplement, "Isotropic Gaussian on SO(3)").

``IG_SO(3)(ε)`` is the heat kernel on SO(3): the law of a rotation whose density with respect to
the Haar measure *normalised to total mass 1* depends only on the rotation angle ω ∈ [0, π],

    f_ε(ω) = Σ_{l≥0} (2l+1) e^{−l(l+1)ε} sin((l+½)ω) / sin(ω/2)                    (Eq. 14)

(equation numbers are those of the tex source, ``eq:igso3_infinite``; see ``docs/conventions.md``).
The axis is uniform on S² and the angle has the density ``(1 − cos ω)/π · f_ε(ω)`` on [0, π]
(the paper's "normalizing factor" ``Z(φ)``). For small ε the series converges slowly and the
closed form (Eq. 15, ``eq:igso3_approx``, obtained from Eq. 14 by Poisson summation keeping the
wraps k ∈ {−1, 0, 1})

    f_ε(ω) ≈ √π ε^{−3/2} e^{ε/4 − (ω/2)²/ε}
             · (ω − e^{−π²/ε}((ω − 2π) e^{πω/ε} + (ω + 2π) e^{−πω/ε})) / (2 sin(ω/2))   (Eq. 15)

is used instead. Its neglected wraps |k| ≥ 2 are relatively ``≈ 3 e^{−2π²/ε}``: 8e-9 at ε = 1
(measured: max relative difference to the series over ω ∈ [0, π] is 4.0e-9 at ε = 1), 8e-5 at
ε = 2 and 3 % at ε = 5 (measured), so ``method="auto"`` uses Eq. 15 for ε < 1 (where the paper says it is
accurate) and the series for ε ≥ 1 (where 7 terms suffice).

**Parameterisation by σ.** posediff uses ``ε = σ²/2`` (:func:`eps_from_sigma`; the authors' code
uses ``(σ/√2)²``, the same): as σ → 0, Eq. 15 becomes ``∝ exp(−ω²/(2σ²))`` and the rotation vector
of ``IG_SO(3)(σ²/2)`` tends to the concentrated Gaussian ``N(0, σ² I₃)`` of the
:class:`~posediff.diffusion.kernels.ConcentratedGaussian` kernel.

**Numerics.** Both evaluations are done in log space and are exact to round-off in float64 and
finite (values and ω-gradients) in float32 for ω ∈ [0, π] and σ down to 1e-6 (ε = 5e-13):

* Eq. 15 is rewritten as ``log f = ½ log π − 3/2 log ε + ε/4 − ω²/(4ε) + log H + log((ω/2)/sin(ω/2))``
  with ``H = B/ω = 1 − E₁ − E₂ − 2π E₁ expm1(−2aω)/ω``, ``a = π/ε``, ``E₁ = e^{−a(π−ω)}``,
  ``E₂ = e^{−a(π+ω)}`` — every exponent is ≤ 0, so nothing over/underflows as ε → 0, and the
  removable singularities at ω = 0 (``expm1(−y)/y`` and ``x/sin x``) use Taylor branches.
* The series evaluates ``sin((l+½)ω)/sin(ω/2)`` as the Dirichlet kernel
  ``1 + 2 Σ_{k=1}^{l} cos(kω)`` (identical, but with no 0/0 at ω = 0 and smooth gradients
  everywhere). It is truncated at the smallest ``lmax`` with ``lmax(lmax+1)·ε ≥ 40`` (:func:`igso3_series_lmax`): the neglected tail is < 1e-15 of f(0)
  (relative to the maximum of f, which is f(0)). For small ε the series suffers cancellation
  where f is tiny: its absolute error is ~1e-16·f(0) (measured relative error ≤ 1.1e-8 where
  f ≥ 1e-8·f(0), for ε ≥ 1e-3; meaningless in the far tail); use the closed form there.
* The angle may be any real: f is even and 2π-periodic in ω (it is a class function), so ω is
  folded into [0, π] first.

**Sampling** (:func:`sample_igso3`) is by inverse CDF of the angle from a quantile table built
once per process (see :func:`igso3_quantile_table`), with the exact σ → 0 limit below the table
and exact Haar-uniform angles above it.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from .kernels import NoiseKernel, broadcast_sigma

__all__ = [
    "IGSO3",
    "IGSO3QuantileTable",
    "eps_from_sigma",
    "igso3_angle_quantile",
    "igso3_dlog_density",
    "igso3_log_density",
    "igso3_quantile_table",
    "igso3_series_lmax",
    "sample_igso3",
    "sample_igso3_angle",
]

#: ``method="auto"`` uses Eq. 15 for ε below this and the series (Eq. 14) at and above it.
EPS_SWITCH = 1.0
#: truncation of the series: the smallest lmax with lmax·(lmax+1)·ε ≥ SERIES_DECAY.
SERIES_DECAY = 40.0
_METHODS = ("auto", "series", "closed_form")
_LOG_SQRT_PI = 0.5 * math.log(math.pi)
_TWO_PI = 2.0 * math.pi


def eps_from_sigma(sigma: Tensor | float) -> Tensor | float:
    """The concentration ``ε = σ²/2`` of ``IG_SO(3)`` whose σ → 0 limit is ``N(0, σ² I₃)``.

    With ε = σ²/2 the small-ε form (Eq. 15) is ``∝ exp(−ω²/(4ε)) = exp(−ω²/(2σ²))``, the density of
    the norm of an isotropic 3-D Gaussian with standard deviation σ per component.
    """
    return sigma * sigma / 2.0


def igso3_series_lmax(eps: float) -> int:
    """Default truncation of Eq. 14: the smallest ``lmax`` with ``lmax(lmax+1)·ε ≥ 40``.

    The first neglected term is ≤ ``(2l+1)² e^{−40}`` and the tail sum is < 1e-15 of f(0) for
    every ε (``f(0) = Σ (2l+1)² e^{−l(l+1)ε} ≈ (√π/2)·ε^{−3/2}`` for small ε, ≥ 1 always).
    """
    if not eps > 0:
        raise ValueError(f"igso3_series_lmax: ε must be positive, got {eps}")
    return max(1, math.ceil((math.sqrt(1.0 + 4.0 * SERIES_DECAY / eps) - 1.0) / 2.0))


def _prepare(omega: Tensor | float, eps: Tensor | float) -> tuple[Tensor, Tensor, torch.dtype]:
    """Broadcast (ω, ε) to a common floating shape; compute in ≥ float32; fold ω into [0, π]."""
    if not isinstance(omega, Tensor):
        omega = torch.as_tensor(omega, dtype=eps.dtype if isinstance(eps, Tensor) else None)
    if not omega.is_floating_point():
        omega = omega.to(torch.get_default_dtype())
    if not isinstance(eps, Tensor):
        eps = torch.as_tensor(eps, dtype=omega.dtype, device=omega.device)
    dtype = torch.promote_types(omega.dtype, eps.dtype) if eps.is_floating_point() else omega.dtype
    work = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
    om, ep = torch.broadcast_tensors(omega.to(work), eps.to(work))
    # f is even and 2π-periodic in ω: fold into [0, π] (a no-op, gradient 1, on [0, π]).
    w = torch.remainder(om.abs(), _TWO_PI)
    w = torch.where(w > math.pi, _TWO_PI - w, w)
    return w, ep, dtype


def _log_x_over_sin_x(x: Tensor) -> Tensor:
    """``log(x / sin x)`` for x ∈ [0, π/2], with its Taylor series x²/6 + x⁴/180 + x⁶/2835 below 1e-2."""
    small = x < 1e-2
    xs = torch.where(small, torch.ones_like(x), x)
    xt = torch.where(small, x, torch.zeros_like(x))
    x2 = xt * xt
    taylor = x2 * (1.0 / 6.0 + x2 * (1.0 / 180.0 + x2 / 2835.0))
    return torch.where(small, taylor, torch.log(xs / torch.sin(xs)))


def _one_minus_exp_neg_over(y: Tensor) -> Tensor:
    """``(1 − e^{−y})/y = −expm1(−y)/y`` for y ≥ 0, with its Taylor series below 1e-3."""
    small = y < 1e-3
    ys = torch.where(small, torch.ones_like(y), y)
    yt = torch.where(small, y, torch.zeros_like(y))  # both branches on safe inputs (finite gradients)
    taylor = 1.0 - yt * (0.5 - yt * (1.0 / 6.0 - yt * (1.0 / 24.0 - yt / 120.0)))
    return torch.where(small, taylor, -torch.expm1(-ys) / ys)


def _log_f_closed_form(w: Tensor, eps: Tensor) -> Tensor:
    """log of Eq. 15 for ω ∈ [0, π], ε > 0, evaluated without over/underflow (module docstring)."""
    a = math.pi / eps
    # ω ≤ π in working precision after the fold, so π − ω ≥ 0 (no clamp: it would zero the gradient at π)
    e1 = torch.exp(-a * (math.pi - w))
    e2 = torch.exp(-a * (math.pi + w))
    # H = B/ω with B the bracket of Eq. 15: B = ω + (2π − ω)E₁ − (2π + ω)E₂, and
    # (E₁ − E₂)/ω = E₁ (1 − e^{−2aω})/ω = 2a E₁ g(2aω).
    h = 1.0 - e1 - e2 + (4.0 * math.pi) * (a * e1) * _one_minus_exp_neg_over(2.0 * a * w)
    return (
        _LOG_SQRT_PI
        - 1.5 * torch.log(eps)
        + 0.25 * eps
        - w * w / (4.0 * eps)
        + torch.log(h)
        + _log_x_over_sin_x(0.5 * w)
    )


def _log_f_series(w: Tensor, eps: Tensor, lmax: int) -> Tensor:
    """log of Eq. 14 truncated at ``lmax`` (inclusive), for ω ∈ [0, π].

    The character ``sin((l+½)ω)/sin(ω/2)`` is evaluated as the Dirichlet kernel
    ``D_l(ω) = 1 + 2 Σ_{k=1}^{l} cos(kω)`` (the same function, with no 0/0 at ω = 0 and smooth
    gradients everywhere), accumulated over l in chunks of ``(numel, chunk)`` at most 2²² entries.
    """
    total = torch.zeros_like(w)
    d_prev = torch.ones_like(w)  # D_{l−1} carried across chunks (D_0 = 1)
    chunk = max(1, min(lmax + 1, (1 << 22) // max(1, w.numel())))
    for start in range(0, lmax + 1, chunk):
        ell = torch.arange(start, min(lmax + 1, start + chunk), dtype=w.dtype, device=w.device)
        # D_l = D_{l−1} + 2 cos(lω) for l ≥ 1; l = 0 adds nothing to D_0 = 1
        cos_terms = (2.0 * (ell > 0).to(w.dtype)) * torch.cos(ell * w.unsqueeze(-1))
        dirichlet = d_prev.unsqueeze(-1) + torch.cumsum(cos_terms, dim=-1)
        weight = (2.0 * ell + 1.0) * torch.exp(-(ell * (ell + 1.0)) * eps.unsqueeze(-1))
        total = total + (weight * dirichlet).sum(-1)
        d_prev = dirichlet[..., -1]
    tiny = torch.finfo(w.dtype).tiny
    return torch.log(total.clamp_min(tiny))


def igso3_log_density(
    omega: Tensor | float,
    eps: Tensor | float,
    *,
    method: str = "auto",
    lmax: int | None = None,
) -> Tensor:
    """``log f_ε(ω)``: the log density of ``IG_SO(3)(ε)`` w.r.t. the Haar measure of total mass 1.

    Args:
        omega: rotation angle(s) ω (any real: f is even and 2π-periodic, ω is folded into [0, π]).
        eps: concentration ε > 0 (``ε = σ²/2``, :func:`eps_from_sigma`), broadcast against ``omega``.
        method: ``"series"`` (Eq. 14 truncated at ``lmax``), ``"closed_form"`` (Eq. 15, the small-ε
            approximation, in log space), or ``"auto"`` (Eq. 15 for ε < 1, the series for ε ≥ 1;
            max relative difference at the switch 4.0e-9).
        lmax: truncation of the series (default :func:`igso3_series_lmax` of the smallest ε).

    The angle density on [0, π] is ``(1 − cos ω)/π · f_ε(ω)``. Exact to round-off in float64,
    finite in float32; differentiable in ω (finite gradients at ω = 0 and ω = π, where they vanish).
    Returns the broadcast shape of ``omega`` and ``eps``.
    """
    if method not in _METHODS:
        raise ValueError(f"igso3_log_density: method must be one of {', '.join(_METHODS)}, got {method!r}")
    w, e, dtype = _prepare(omega, eps)
    if method == "closed_form":
        out = _log_f_closed_form(w, e)
    elif method == "series":
        if lmax is None:
            if w.numel() == 0:
                return w.to(dtype)
            lmax = igso3_series_lmax(float(e.min()))
        out = _log_f_series(w, e, int(lmax))
    else:
        use_closed = e < EPS_SWITCH
        e_closed = torch.where(use_closed, e, torch.full_like(e, 0.5 * EPS_SWITCH))
        e_series = torch.where(use_closed, torch.full_like(e, EPS_SWITCH), e)
        lm = igso3_series_lmax(EPS_SWITCH) if lmax is None else int(lmax)
        out = torch.where(use_closed, _log_f_closed_form(w, e_closed), _log_f_series(w, e_series, lm))
    return out.to(dtype)


def igso3_dlog_density(
    omega: Tensor | float,
    eps: Tensor | float,
    *,
    method: str = "auto",
    lmax: int | None = None,
) -> Tensor:
    """``d/dω log f_ε(ω)`` (by autograd of :func:`igso3_log_density` on the scalar function).

    Zero at ω = 0 and (up to the truncation of Eq. 15) at ω = π, by symmetry. The result is not
    itself differentiable (``omega`` and ``eps`` are detached); shape as ``igso3_log_density``.
    """
    omega_t = torch.as_tensor(omega)
    if not omega_t.is_floating_point():
        omega_t = omega_t.to(torch.get_default_dtype())
    eps_t = (
        eps if isinstance(eps, Tensor) else torch.as_tensor(eps, dtype=omega_t.dtype, device=omega_t.device)
    )
    omega_t, eps_t = torch.broadcast_tensors(omega_t.detach(), eps_t.detach())
    with torch.enable_grad():
        w = omega_t.clone().requires_grad_(True)
        lp = igso3_log_density(w, eps_t, method=method, lmax=lmax)
        (grad,) = torch.autograd.grad(lp.sum(), w)
    return grad.to(lp.dtype)


# ---------------------------------------------------------------------------------------- sampling
#: σ range of the quantile table (log-spaced rows).
TABLE_SIGMA_MIN = 1e-3
TABLE_SIGMA_MAX = 4.0
TABLE_NUM_SIGMA = 256
#: quantile levels u_m = sin²(π m / (2(M − 1))), m = 0 … M − 1 (spacing ≈ 2.4e-6 at both ends).
TABLE_NUM_U = 1025
#: fine angle grid for the CDF of row k: ω_j = ω_max,k (j/(N − 1))³, ω_max,k = min(π, 12 σ_k).
TABLE_NUM_OMEGA = 4097
TABLE_OMEGA_MAX_SIGMAS = 12.0


@dataclass(frozen=True)
class IGSO3QuantileTable:
    """Quantiles of the ``IG_SO(3)`` angle, ``Q[k, m] = CDF⁻¹(u_m; σ_k)``, stored as ``Q/σ``.

    Attributes:
        sigmas: ``(K,)`` log-spaced σ_k from :data:`TABLE_SIGMA_MIN` (1e-3) to :data:`TABLE_SIGMA_MAX` (4).
        u: ``(M,)`` quantile levels ``u_m = sin²(π s_m / 2)``, ``s_m = m/(M−1)`` (dense near 0 and 1).
        ratio: ``(K, M)`` ``Q[k, m] / σ_k``; it tends to the chi(3) quantile as σ → 0, so interpolating
            it in log σ is exact in that limit.
        mass: ``(K,)`` the trapezoid integral of the angle density before normalising (≈ 1).
        build_seconds: time the float64 master table took to build.
    """

    sigmas: Tensor
    u: Tensor
    ratio: Tensor
    mass: Tensor
    build_seconds: float

    @property
    def log_sigma_min(self) -> float:
        return math.log(TABLE_SIGMA_MIN)

    @property
    def d_log_sigma(self) -> float:
        return (math.log(TABLE_SIGMA_MAX) - math.log(TABLE_SIGMA_MIN)) / (self.sigmas.shape[0] - 1)

    def to(self, dtype: torch.dtype, device: Any) -> IGSO3QuantileTable:
        return IGSO3QuantileTable(
            self.sigmas.to(dtype=dtype, device=device),
            self.u.to(dtype=dtype, device=device),
            self.ratio.to(dtype=dtype, device=device).contiguous(),
            self.mass.to(dtype=dtype, device=device),
            self.build_seconds,
        )


_TABLES: dict[tuple[torch.dtype, str], IGSO3QuantileTable] = {}
_TABLE_LOCK = threading.Lock()
#: how many times the float64 master table was built in this process (1 after first use).
TABLE_BUILDS = 0


def _table_u(num_u: int = TABLE_NUM_U) -> Tensor:
    s = torch.linspace(0.0, 1.0, num_u, dtype=torch.float64)
    u = torch.sin(0.5 * math.pi * s) ** 2
    u[0], u[-1] = 0.0, 1.0
    return u


def _build_table(num_omega: int = TABLE_NUM_OMEGA) -> IGSO3QuantileTable:
    """The float64 CPU master table (see :func:`igso3_quantile_table`)."""
    t0 = time.perf_counter()
    sigmas = torch.logspace(
        math.log10(TABLE_SIGMA_MIN), math.log10(TABLE_SIGMA_MAX), TABLE_NUM_SIGMA, dtype=torch.float64
    )
    u = _table_u()
    q, mass = _quantile_rows(sigmas, u, num_omega)
    return IGSO3QuantileTable(sigmas, u, q / sigmas.unsqueeze(-1), mass, time.perf_counter() - t0)


def _quantile_rows(sigmas: Tensor, u: Tensor, num_omega: int = TABLE_NUM_OMEGA) -> tuple[Tensor, Tensor]:
    """Quantiles ``(len(sigmas), len(u))`` of the angle (float64): per-σ CDF by cumulative
    trapezoid on a power grid, inverted by linear interpolation; and the raw integrals."""
    f64 = torch.float64
    sigmas, u = sigmas.to(f64), u.to(f64)
    t = torch.linspace(0.0, 1.0, num_omega, dtype=f64)
    dt = 1.0 / (num_omega - 1)
    lmax = igso3_series_lmax(EPS_SWITCH)
    quantiles, masses = [], []
    for rows in sigmas.split(8):  # 8 rows at a time: bounded memory
        # per-row grid ω = ω_max t³ on [0, ω_max], ω_max = min(π, 12σ) (the mass beyond 12σ is < 1e-30)
        w_max = (TABLE_OMEGA_MAX_SIGMAS * rows).clamp_max(math.pi).unsqueeze(-1)
        omega = w_max * t**3
        eps = torch.as_tensor(eps_from_sigma(rows)).unsqueeze(-1).expand_as(omega)
        closed = rows < EPS_SWITCH**0.5 * math.sqrt(2.0)  # ε = σ²/2 < 1
        log_f = torch.empty_like(omega)  # each row by its "auto" branch only
        log_f[closed] = _log_f_closed_form(omega[closed], eps[closed])
        log_f[~closed] = _log_f_series(omega[~closed], eps[~closed], lmax)
        # integrand in t: (1 − cos ω)/π · f_ε(ω) · dω/dt (smooth in t, ∝ t⁸ near 0)
        log_jac = torch.log(2.0 * torch.sin(0.5 * omega) ** 2 / math.pi * (3.0 * w_max * t**2))
        dens = torch.exp(log_f + log_jac)
        cdf = torch.cumsum(0.5 * (dens[:, 1:] + dens[:, :-1]) * dt, dim=-1)
        cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1)
        mass = cdf[:, -1:].clone()
        cdf = cdf / mass
        target = u.expand(rows.shape[0], -1).contiguous()
        j = torch.searchsorted(cdf, target).clamp(1, num_omega - 1)
        c_lo, c_hi = cdf.gather(-1, j - 1), cdf.gather(-1, j)
        w_lo, w_hi = omega.gather(-1, j - 1), omega.gather(-1, j)
        frac = ((target - c_lo) / (c_hi - c_lo).clamp_min(1e-300)).clamp(0.0, 1.0)
        q = w_lo + frac * (w_hi - w_lo)
        # u = 1: the end of the support up to 1e-13 of mass (the float CDF may reach 1 only at ω_max)
        j_end = torch.searchsorted(cdf, torch.full_like(cdf[:, :1], 1.0 - 1e-13)).clamp(0, num_omega - 1)
        q[:, -1:] = omega.gather(-1, j_end)
        q[:, 0] = 0.0
        quantiles.append(q)
        masses.append(mass.squeeze(-1))
    return torch.cat(quantiles), torch.cat(masses)


def igso3_quantile_table(dtype: torch.dtype = torch.float64, device: Any = "cpu") -> IGSO3QuantileTable:
    """The process-wide quantile table of the ``IG_SO(3)`` angle, built lazily once (≈ 0.3 s on one core).

    The float64 CPU master is computed on first use (``TABLE_BUILDS`` counts it) from the angle
    density ``(1 − cos ω)/π · f_ε(ω)`` (``method="auto"``, ε = σ²/2) for 256 σ_k log-spaced from
    1e-3 to 4. Row k uses the power grid ``ω_j = ω_max (j/4096)³`` on ``[0, ω_max]``,
    ``ω_max = min(π, 12σ_k)`` (dense near 0; the mass beyond 12σ is < 1e-30), a cumulative
    trapezoid rule in ``t = (ω/ω_max)^{1/3}`` (integrand ∝ t⁸ near 0, smooth), normalisation by
    the total (the raw total, 1 ± 6e-8, is kept in ``mass``), and inversion by linear interpolation
    at 1025 levels ``u_m = sin²(π m/2048)`` (spacing 2.4e-6 at both ends). Measured against a
    16× finer grid, the quantiles are accurate to 9e-6 rad (2e-5 relative). Copies per
    (dtype, device) are cached next to the master; the cache is thread-safe.
    """
    global TABLE_BUILDS
    dev = torch.device(device)
    key = (dtype, str(dev))
    table = _TABLES.get(key)
    if table is not None:
        return table
    with _TABLE_LOCK:
        master_key = (torch.float64, "cpu")
        master = _TABLES.get(master_key)
        if master is None:
            master = _build_table()
            TABLE_BUILDS += 1
            _TABLES[master_key] = master
        if key not in _TABLES:
            _TABLES[key] = master.to(dtype, dev)
        return _TABLES[key]


def igso3_angle_quantile(sigma: Tensor | float, u: Tensor | float) -> Tensor:
    """The angle quantile ``CDF⁻¹(u; σ)`` interpolated in the table (:func:`igso3_quantile_table`).

    The table stores ``Q/σ``; it is interpolated with 4-point (cubic Lagrange) weights in log σ
    and linearly in ``s = (2/π) asin √u`` (the coordinate in which the u levels are uniform).
    Measured as the CDF error of the interpolated quantile, ``max_u |F_σ(Q̂(σ, u)) − u|``, at σ
    half-way between rows: ≤ 4e-6 for every σ in the table (bilinear interpolation in (log σ, s)
    would give 2.6e-4 for σ ∈ [1, 4], where the law saturates to Haar; ≤ 1e-5 below σ = 0.7).
    σ outside [1e-3, 4] is clamped to the table in log σ and the result scaled by σ (so below
    1e-3 this is the σ → 0 limit σ·chi₃⁻¹(u), to O(1e-7)); above 4 the law is Haar to < 1e-6.
    """
    sigma_t = torch.as_tensor(
        sigma, dtype=u.dtype if isinstance(u, Tensor) and u.is_floating_point() else None
    )
    if not sigma_t.is_floating_point():
        sigma_t = sigma_t.to(torch.get_default_dtype())
    u_t = torch.as_tensor(u, dtype=sigma_t.dtype, device=sigma_t.device)
    sigma_t, u_t = torch.broadcast_tensors(sigma_t, u_t)
    table = igso3_quantile_table(sigma_t.dtype, sigma_t.device)
    k_max, m_max = table.ratio.shape[0] - 1, table.ratio.shape[1] - 1
    log_s = torch.log(sigma_t.clamp_min(torch.finfo(sigma_t.dtype).tiny))
    pos = ((log_s - table.log_sigma_min) / table.d_log_sigma).clamp(0.0, float(k_max))
    # rows k0 … k0+3 around pos (one-sided at the ends), x = pos − k0 ∈ [0, 3]
    k0 = (pos.floor() - 1.0).clamp(0, k_max - 3)
    x = pos - k0
    xm1, xm2, xm3 = x - 1.0, x - 2.0, x - 3.0
    weights = (
        -xm1 * xm2 * xm3 / 6.0,
        x * xm2 * xm3 / 2.0,
        -x * xm1 * xm3 / 2.0,
        x * xm1 * xm2 / 6.0,
    )
    s = (2.0 / math.pi) * torch.asin(u_t.clamp(0.0, 1.0).sqrt()) * m_max
    m0 = s.floor().clamp(0, m_max - 1)
    tm = s - m0
    flat = table.ratio.reshape(-1)
    idx = (k0.long() * (m_max + 1) + m0.long()).reshape(-1)
    ratio = torch.zeros_like(s)
    for r, w in enumerate(weights):
        at = idx + r * (m_max + 1)
        ratio = ratio + w * ((1 - tm) * flat[at].view_as(s) + tm * flat[at + 1].view_as(s))
    return (sigma_t * ratio).clamp(0.0, math.pi)


def _sample(sigma: Tensor, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """Rotation vectors ``(*b, 3)`` of ``IG_SO(3)(σ²/2)`` and their angles ``(*b,)``."""
    sigma = sigma.detach()
    shape, dtype, device = tuple(sigma.shape), sigma.dtype, sigma.device
    g = torch.randn((*shape, 4), generator=generator, dtype=dtype, device=device)
    u = torch.rand(shape, generator=generator, dtype=dtype, device=device)
    n, w = g[..., :3], g[..., 3]
    r = n.norm(dim=-1)
    r_safe = torch.where(r > 0, r, torch.ones_like(r))
    axis = n / r_safe.unsqueeze(-1)
    # σ in the table: inverse CDF; above it: the Haar angle of the uniform quaternion (w, n)/|(w, n)|.
    omega = torch.where(
        sigma > TABLE_SIGMA_MAX, 2.0 * torch.atan2(r, w.abs()), igso3_angle_quantile(sigma, u)
    )
    phi = omega.unsqueeze(-1) * axis
    # below the table: the σ → 0 limit exactly, φ = σ n (ω = σ|n|, a chi(3) angle)
    small = sigma < TABLE_SIGMA_MIN
    phi = torch.where(small.unsqueeze(-1), sigma.unsqueeze(-1) * n, phi)
    omega = torch.where(small, sigma * r, omega)
    return phi, omega


def sample_igso3(
    sigma: Tensor | float,
    *,
    batch_shape: tuple[int, ...] | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: Any = None,
) -> Tensor:
    """Rotation vectors ``φ (*batch_shape, 3)`` with ``Exp(φ) ~ IG_SO(3)(ε = σ²/2)``, per-sample σ.

    The angle is drawn by inverse CDF (:func:`igso3_angle_quantile`, one uniform per sample)
    for σ ∈ [1e-3, 4]; below 1e-3 it is the σ → 0 limit exactly, ``φ = σ n`` with
    ``n ~ N(0, I₃)`` (numerically safe as ε → 0, and σ = 0 gives φ = 0); above 4 the angle is that
    of a Haar-uniform rotation (the IG law is Haar to < 1e-6 there). The axis is uniform on S²
    (a normalised Gaussian). All randomness comes from ``generator``. Angles lie in [0, π].
    """
    return _sample(broadcast_sigma(sigma, batch_shape, dtype, device), generator)[0]


def sample_igso3_angle(
    sigma: Tensor | float,
    *,
    batch_shape: tuple[int, ...] | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: Any = None,
) -> Tensor:
    """The angles ``|φ|`` of :func:`sample_igso3` (same draws for the same generator state)."""
    return _sample(broadcast_sigma(sigma, batch_shape, dtype, device), generator)[1]


# ------------------------------------------------------------------------------------------ kernel
class IGSO3(NoiseKernel, name="igso3"):
    """Isotropic Gaussian on the rotation, ordinary Gaussian on the translation (paper supp. Eq. 14–15).

    With per-component σ from the base class (``σ_r = σ·rotation_scale``,
    ``σ_t = σ·translation_scale``), the tangent ``z = [ρ, φ]`` of ``X̃ = X·Exp(z)`` has

    * φ: ``Exp(φ) ~ IG_SO(3)(ε)`` with ``ε = σ_r²/2`` (:func:`eps_from_sigma`), so that as σ → 0 this
      kernel and :class:`~posediff.diffusion.kernels.ConcentratedGaussian` coincide;
    * ρ (``r3so3``, ``se3``): ``N(0, σ_t² I₃)``, independent of φ.

    **Reference measure** of ``log_prob``/``log_prob_tangent``: the Haar measure of SO(3)
    normalised to *total mass 1* on the rotation (so the rotation factor is ``f_ε(|φ|)`` itself),
    times Lebesgue measure ``dρ`` on the translation coordinates::

        log q(z) = log f_ε(|φ|) − ½ Σ ρ_i²/σ_t² − 3 log σ_t − (3/2) log 2π.

    This differs from :class:`ConcentratedGaussian`, whose Haar reference agrees with Lebesgue
    measure in exponential coordinates at the identity (``|det J_r(φ)| dφ``, total mass 8π²):
    Haar(mass 1) = (1/(8π²))·Haar(Lebesgue at identity), so the ConcentratedGaussian-style log
    density of this kernel is ``log q − log 8π²``, and the density w.r.t. Lebesgue ``dφ`` in the
    tangent is ``f_ε(θ)·(2(1 − cos θ)/θ²)/(8π²)``, θ = |φ|. For ``r3so3`` ρ = t, so the
    reference is the group's Haar measure ``dR(mass 1) × dt``; for ``se3`` the translation is
    ``t = J_l(φ)ρ`` (SO(3) left Jacobian), ``dt = |det J_l(φ)| dρ`` with
    ``|det J_l(φ)| = 2(1 − cos θ)/θ²``, so the density w.r.t. the SE(3) Haar measure
    ``dR(mass 1) × dt`` is ``q(z) / |det J_l(φ)|`` (the score here is that of ``q``, as for the
    other kernels).

    Score: ``∇_z log q = [−ρ/σ_t², (d log f/dω)(|φ|)·φ/|φ|]`` (0 at φ = 0 by symmetry, finite at
    |φ| = π); the base class applies ``J_r⁻ᵀ(z)``, which leaves the SO(3) part unchanged because
    ``J_r⁻ᵀ(φ)φ = φ``.

    Sampling: :func:`sample_igso3` (inverse CDF from a table built once per process).
    """

    supported_groups: ClassVar[tuple[str, ...] | None] = ("so3", "r3so3", "se3")

    def _rot_index(self) -> tuple[slice, list[int]]:
        sl = self.group.rotation_slice
        rot = set(range(self.dim)[sl])
        return sl, [i for i in range(self.dim) if i not in rot]

    def _sample_tangent(self, sigma: Tensor, generator: torch.Generator | None) -> Tensor:
        sl, trans = self._rot_index()
        z = torch.empty((*sigma.shape, self.dim), dtype=sigma.dtype, device=sigma.device)
        if trans:
            rho = torch.randn(
                (*sigma.shape, len(trans)), generator=generator, dtype=sigma.dtype, device=sigma.device
            )
            z[..., trans] = rho * (sigma * self.translation_scale).unsqueeze(-1)
        z[..., sl] = _sample(sigma * self.rotation_scale, generator)[0]
        return z

    def _parts(
        self, z: Tensor, sigma_c: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None]:
        sl, trans = self._rot_index()
        phi = z[..., sl]
        sigma_r = sigma_c[..., sl.start]
        theta2 = (phi * phi).sum(-1)
        pos = theta2 > 0
        omega = torch.where(
            pos, torch.where(pos, theta2, torch.ones_like(theta2)).sqrt(), torch.zeros_like(theta2)
        )
        if not trans:
            return phi, omega, sigma_r, None, None
        return phi, omega, sigma_r, z[..., trans], sigma_c[..., trans]

    def _log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        _, omega, sigma_r, rho, sigma_t = self._parts(z, sigma_c)
        lp = igso3_log_density(omega, eps_from_sigma(sigma_r))
        if rho is not None and sigma_t is not None:
            k = rho.shape[-1]
            lp = (
                lp
                + (-0.5 * (rho / sigma_t) ** 2 - torch.log(sigma_t)).sum(-1)
                - 0.5 * k * math.log(2 * math.pi)
            )
        return lp

    def _grad_log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        sl, trans = self._rot_index()
        phi, omega, sigma_r, rho, sigma_t = self._parts(z, sigma_c)
        dlog = igso3_dlog_density(omega, eps_from_sigma(sigma_r))
        pos = omega > 0
        unit = phi / torch.where(pos, omega, torch.ones_like(omega)).unsqueeze(-1)
        grad = torch.zeros_like(z)
        grad[..., sl] = torch.where(pos.unsqueeze(-1), dlog.unsqueeze(-1) * unit, torch.zeros_like(phi))
        if rho is not None and sigma_t is not None:
            grad[..., trans] = -rho / sigma_t**2
        return grad
