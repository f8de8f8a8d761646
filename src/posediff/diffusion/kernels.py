"""Noise kernels on a Lie group: the perturbation ``X̃ = X · Exp(z)`` and its density and score.

A kernel is the forward-process distribution ``p_σ(X̃ | X)`` of the paper (Eq. 3, tex numbering;
see ``docs/conventions.md`` for the equation map). It is written entirely in the *tangent* of
the right perturbation, ``z = Log(X⁻¹ X̃)``, because every kernel here is left-invariant:
``p_σ(X̃ | X) = q_σ(Log(X⁻¹ X̃))``.

Every kernel provides

* ``sample_tangent(sigma)`` → ``z`` and ``sample(X, sigma)`` → ``(X̃, z)``;
* ``log_prob_tangent(z, sigma)`` and ``log_prob(X̃, X, sigma)``, w.r.t. the reference measure the
  class documents;
* ``score_tangent(z, sigma)`` / ``score(X̃, X, sigma)``: the exact Stein score, the gradient of
  ``log p`` with respect to a right perturbation of ``X̃`` (paper Eq. 4),
  ``∇ log p = J_r⁻ᵀ(z) ∇_z log q_σ(z)`` — the chain rule through ``Log(Exp(z)·Exp(τ)) ≈ z + J_r⁻¹(z) τ``.

``sigma`` is a tensor broadcastable to the batch shape ``z.shape[:-1]`` (or a float). A kernel may
scale translation and rotation components differently: the per-component standard deviation is
``sigma * kernel.scales`` (``translation_scale`` on ρ, ``rotation_scale`` on φ).

Kernels register by subclassing (``class MyKernel(NoiseKernel, name="my")``); the contract tests
in ``posediff.testing.diffusion`` run over ``NoiseKernel.registry``.
"""

import math
from typing import Any, ClassVar

import torch
from torch import Tensor

from .._registry import Registered
from ..lie import LieGroup, get_group


def broadcast_sigma(
    sigma: Tensor | float, batch_shape: tuple[int, ...] | None, dtype: torch.dtype | None, device: Any
) -> Tensor:
    """σ as a floating tensor broadcast to ``batch_shape`` (default: σ's own shape)."""
    sig = torch.as_tensor(sigma, dtype=dtype, device=device)
    if not sig.is_floating_point():
        sig = sig.to(torch.get_default_dtype())
    shape = tuple(sig.shape) if batch_shape is None else tuple(batch_shape)
    return torch.broadcast_to(sig, shape)


class NoiseKernel(Registered, family=True):
    """A left-invariant perturbation kernel ``p_σ(X̃ | X) = q_σ(Log(X⁻¹ X̃))`` on a Lie group.

    Args:
        group: the Lie group (an instance or a registered name).
        translation_scale: multiplies σ on the translation components ρ.
        rotation_scale: multiplies σ on the rotation components φ.
        wrap: return the principal tangent ``Log(Exp(z))`` from ``sample``/``sample_tangent`` (the
            group element is the same; only the label changes when a rotation angle exceeds π).
            The authors' code wraps its rotation noise; the density of Eq. 3 is written in
            principal coordinates, so wrapped labels are the consistent regression targets.
    """

    family_label: ClassVar[str] = "noise kernel"
    name: ClassVar[str]
    #: groups the kernel supports (None: every group)
    supported_groups: ClassVar[tuple[str, ...] | None] = None

    def __init__(
        self,
        group: LieGroup | str,
        *,
        translation_scale: float = 1.0,
        rotation_scale: float = 1.0,
        wrap: bool = True,
    ) -> None:
        self.group = get_group(group) if isinstance(group, str) else group
        if not isinstance(self.group, LieGroup):
            raise TypeError(f"{type(self).__name__}: group must be a LieGroup or a name, got {group!r}")
        if self.supported_groups is not None and self.group.name not in self.supported_groups:
            raise ValueError(
                f"{type(self).__name__} supports the groups {', '.join(self.supported_groups)}, "
                f"not {self.group.name!r}"
            )
        if translation_scale <= 0 or rotation_scale <= 0:
            raise ValueError(f"{type(self).__name__}: component scales must be positive")
        self.translation_scale = float(translation_scale)
        self.rotation_scale = float(rotation_scale)
        self.wrap = bool(wrap)

    def __repr__(self) -> str:
        extra = ""
        if self.translation_scale != 1.0 or self.rotation_scale != 1.0:
            extra = f", translation_scale={self.translation_scale}, rotation_scale={self.rotation_scale}"
        return f"{type(self).__name__}({self.group.name!r}{extra})"

    # ------------------------------------------------------------------ shapes
    @property
    def dim(self) -> int:
        return self.group.dim

    def scales(self, *, dtype: torch.dtype | None = None, device: Any = None) -> Tensor:
        """Per-component multipliers of σ, ``(dim,)``: ``translation_scale`` on ρ, ``rotation_scale`` on φ."""
        s = torch.full(
            (self.dim,), self.translation_scale, dtype=dtype or torch.get_default_dtype(), device=device
        )
        s[self.group.rotation_slice] = self.rotation_scale
        return s

    def component_sigma(self, sigma: Tensor | float, like: Tensor) -> Tensor:
        """σ per tangent component, ``(*b, dim)``, from ``sigma`` broadcastable to ``like.shape[:-1]``."""
        sigma = torch.as_tensor(sigma, dtype=like.dtype, device=like.device)
        return sigma.unsqueeze(-1) * self.scales(dtype=like.dtype, device=like.device)

    # ------------------------------------------------------------------ sampling
    def sample_tangent(
        self,
        sigma: Tensor | float,
        *,
        batch_shape: tuple[int, ...] | None = None,
        generator: torch.Generator | None = None,
        dtype: torch.dtype | None = None,
        device: Any = None,
    ) -> Tensor:
        """Draw ``z`` with ``X̃ = X · Exp(z) ~ p_σ(· | X)``: shape ``(*batch_shape, dim)``.

        ``batch_shape`` defaults to ``sigma``'s shape.
        """
        z = self._sample_tangent(broadcast_sigma(sigma, batch_shape, dtype, device), generator)
        if self.wrap:
            z = self._wrap(z)
        return z

    def sample(
        self, x: Tensor, sigma: Tensor | float, *, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(X̃, z)`` with ``X̃ = X · Exp(z)`` for a batch of means ``X (*b, n, n)``."""
        batch = tuple(x.shape[:-2])
        z = self.sample_tangent(sigma, batch_shape=batch, generator=generator, dtype=x.dtype, device=x.device)
        return self.group.rplus(x, z), z

    # ------------------------------------------------------------------ density and score
    def log_prob_tangent(self, z: Tensor, sigma: Tensor | float) -> Tensor:
        """``log q_σ(z)``: the log density at ``X̃ = X · Exp(z)`` (``z`` principal), shape ``z.shape[:-1]``."""
        return self._log_prob_tangent(z, self.component_sigma(sigma, z))

    def log_prob(self, x_noisy: Tensor, x: Tensor, sigma: Tensor | float) -> Tensor:
        """``log p_σ(X̃ | X) = log q_σ(Log(X⁻¹ X̃))``."""
        return self.log_prob_tangent(self.group.rminus(x, x_noisy), sigma)

    def grad_log_prob_tangent(self, z: Tensor, sigma: Tensor | float) -> Tensor:
        """``∇_z log q_σ(z)`` (Euclidean gradient in the tangent coordinates), ``(*b, dim)``."""
        return self._grad_log_prob_tangent(z, self.component_sigma(sigma, z))

    def score_tangent(self, z: Tensor, sigma: Tensor | float) -> Tensor:
        """The exact Stein score at ``X̃ = X·Exp(z)`` (paper Eq. 4): ``J_r⁻ᵀ(z) ∇_z log q_σ(z)``."""
        grad = self.grad_log_prob_tangent(z, sigma)
        jr_inv = self.group.jac_right_inv(z)
        return (jr_inv.transpose(-1, -2) @ grad.unsqueeze(-1)).squeeze(-1)

    def score(self, x_noisy: Tensor, x: Tensor, sigma: Tensor | float) -> Tensor:
        """The exact Stein score of ``p_σ(· | X)`` at ``X̃``, in the right-trivialised tangent of ``X̃``."""
        return self.score_tangent(self.group.rminus(x, x_noisy), sigma)

    # ------------------------------------------------------------------ to implement
    def _sample_tangent(self, sigma: Tensor, generator: torch.Generator | None) -> Tensor:
        """``(*b, dim)`` samples for ``sigma (*b)`` (not yet wrapped)."""
        raise NotImplementedError

    def _log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        """``log q`` for per-component σ ``sigma_c (*b, dim)``."""
        raise NotImplementedError

    def _grad_log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        """Default: autograd of ``_log_prob_tangent``; override with a closed form when there is one."""
        with torch.enable_grad():
            zz = z.detach().requires_grad_(True)
            lp = self._log_prob_tangent(zz, sigma_c.detach())
            (grad,) = torch.autograd.grad(lp.sum(), zz)
        return grad

    def _wrap(self, z: Tensor) -> Tensor:
        """The principal tangent of ``Exp(z)``, computed only where a rotation angle exceeds π."""
        rot = z[..., self.group.rotation_slice]
        far = rot.norm(dim=-1) > math.pi
        if not bool(far.any()):
            return z
        wrapped = self.group.log(self.group.exp(z))
        return torch.where(far.unsqueeze(-1), wrapped, z)


class ConcentratedGaussian(NoiseKernel, name="gaussian"):
    """The concentrated Gaussian ``N_G(X̃; X, Σ)`` on any group (paper Eq. 3 and Eq. 16–17).

    Sampling: ``z ~ N(0, diag(σ_c²))`` with ``σ_c = σ · scales``, ``X̃ = X · Exp(z)``.

    Density (``log_prob``): paper Eq. 3 with ``ζ(Σ) = (2π)^{k/2} |Σ|^{1/2}``,
    ``log q(z) = −½ Σ_k z_k²/σ_k² − Σ_k log σ_k − (k/2) log 2π``, ``z = Log(X⁻¹X̃)``.
    **Reference measure**: the Haar measure of the group normalised to agree with Lebesgue measure
    in exponential coordinates at the identity (``dHaar = |det J_r(z)| dz`` in the chart ``z``). This
    is the density the paper differentiates (Eq. 4–5). It is *exactly* normalised only as σ → 0: the
    law of ``X·Exp(z)`` with Gaussian ``z`` has Haar density ``N(z)/|det J_r(z)|`` (summed over the
    2π-wrapped preimages of the rotation part), which ``pushforward_log_prob`` returns.

    Score (exact for Eq. 3, paper Eq. 5): ``−J_r⁻ᵀ(z) Σ⁻¹ z``. For SO3 and R3SO3 this equals
    ``−Σ⁻¹ z`` (Eq. 8–10, because ``J_r⁻ᵀ = J_l⁻¹`` there and ``J_l⁻¹(z) z = z``); for SE3 it does not
    (Eq. 11), which is why the paper trains with the surrogate ``−z/σ²`` (Eq. 12).
    """

    def _sample_tangent(self, sigma: Tensor, generator: torch.Generator | None) -> Tensor:
        eps = torch.randn(
            (*sigma.shape, self.dim), generator=generator, dtype=sigma.dtype, device=sigma.device
        )
        return eps * self.component_sigma(sigma, eps)

    def _log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        k = z.shape[-1]
        return (-0.5 * (z / sigma_c) ** 2 - torch.log(sigma_c)).sum(-1) - 0.5 * k * math.log(2 * math.pi)

    def _grad_log_prob_tangent(self, z: Tensor, sigma_c: Tensor) -> Tensor:
        return -z / sigma_c**2

    def pushforward_log_prob(
        self, x_noisy: Tensor, x: Tensor, sigma: Tensor | float, *, wraps: int = 2
    ) -> Tensor:
        """The exact Haar log density of the sampling law ``X·Exp(z)``, ``z ~ N(0, Σ)``.

        ``Σ_k N(z_k) / |det J_r(z_k)|`` over the preimages ``z_k`` of ``X⁻¹X̃`` whose rotation part
        differs from the principal one by ``2πn`` along its axis, ``|n| ≤ wraps``. For semidirect
        groups (SE3, SE2) the translation part of each preimage is re-solved so that ``Exp(z_k)``
        is the same element (``Exp``'s translation is linear in ρ for a fixed rotation part). Same
        reference measure as ``log_prob``. Used to check the kernel, not in training.
        """
        g = self.group
        z0 = g.rminus(x, x_noisy)
        element = g.exp(z0)
        sl = g.rotation_slice
        trans = [i for i in range(g.dim) if i not in range(g.dim)[sl]]
        k = g.matrix_dim - 1
        phi = z0[..., sl]
        theta = phi.norm(dim=-1, keepdim=True)
        axis = torch.where(theta > 1e-12, phi / theta.clamp_min(1e-300), torch.zeros_like(phi))
        if phi.shape[-1] == 1:  # planar rotation: the "axis" is the sign
            axis = torch.where(phi >= 0, torch.ones_like(phi), -torch.ones_like(phi))
        terms = []
        for n in range(-wraps, wraps + 1):
            zn = z0.clone()
            if n != 0:
                zn[..., sl] = phi + 2 * math.pi * n * axis
                if trans:
                    zn = self._resolve_translation(zn, element[..., :k, k], trans)
            term = self.log_prob_tangent(zn, sigma) - torch.log(torch.linalg.det(g.jac_right(zn)).abs())
            if n != 0:
                term = torch.where(theta.squeeze(-1) > 0, term, torch.full_like(term, -math.inf))
            terms.append(term)
        return torch.logsumexp(torch.stack(terms), dim=0)

    def _resolve_translation(self, z: Tensor, t: Tensor, trans: list[int]) -> Tensor:
        """Set the translation components of ``z`` so that ``Exp(z)`` has translation ``t``."""
        g = self.group
        k = g.matrix_dim - 1
        cols = []
        for i in trans:
            zi = z.clone()
            zi[..., trans] = 0.0
            zi[..., i] = 1.0
            cols.append(g.exp(zi)[..., :k, k])
        zero = z.clone()
        zero[..., trans] = 0.0
        offset = g.exp(zero)[..., :k, k]
        A = torch.stack([c - offset for c in cols], dim=-1)  # translation is affine in ρ
        rho = torch.linalg.solve(A, (t - offset).unsqueeze(-1)).squeeze(-1)
        out = z.clone()
        out[..., trans] = rho
        return out
