"""Stein score targets: what the denoising score-matching loss regresses (paper Eq. 6).

``stein_score(group, z, sigma, method)`` is the one public entry point; the methods are a
registry (``ScoreTarget.registry``), so a new target is a subclass and is contract-tested
automatically.

For a noisy pose ``X̃ = X · Exp(z)`` drawn from a kernel (default: the concentrated Gaussian of
paper Eq. 3 with ``Σ = σ²I``):

* ``surrogate`` — ``−z/σ²`` (paper Eq. 12): the direction that undoes the perturbation exactly,
  ``X̃ · Exp(σ² · s) = X``. Cheap and, the paper argues, better at few sampling steps on SE(3).
* ``closed_form`` — the exact score of the kernel density, ``−J_r⁻ᵀ(z) z/σ²`` for the Gaussian
  (paper Eq. 5; ``kernel.score_tangent`` in general).
* ``autograd`` — the same exact score computed by differentiating ``log p(X̃·Exp(τ) | X)`` with
  respect to ``τ`` at ``τ = 0`` through the group's ``rplus`` (supplement, Eq. 18), the way the
  paper's ablation does it.

On SO3 and R3SO3 all three agree (``J_r⁻ᵀ = J_l⁻¹`` and ``J_l⁻¹(z) z = z``, Eq. 8–10). On SE3 the
exact score differs from the surrogate whenever rotation and translation noise are coupled
(Eq. 11).
"""

from typing import ClassVar

import torch
from torch import Tensor

from .._registry import Registered
from ..lie import LieGroup, get_group
from .kernels import ConcentratedGaussian, NoiseKernel


class ScoreTarget(Registered, family=True):
    """A way to compute the Stein score of ``p_σ(X̃ | X)`` at ``X̃ = X · Exp(z)``."""

    family_label: ClassVar[str] = "score target"
    name: ClassVar[str]

    def __call__(self, kernel: NoiseKernel, z: Tensor, sigma: Tensor | float) -> Tensor:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class SurrogateScore(ScoreTarget, name="surrogate"):
    """``−z/σ_c²`` per component (paper Eq. 12); ignores the kernel's density."""

    def __call__(self, kernel: NoiseKernel, z: Tensor, sigma: Tensor | float) -> Tensor:
        return -z / kernel.component_sigma(sigma, z) ** 2


class ClosedFormScore(ScoreTarget, name="closed_form"):
    """The kernel's exact score, ``J_r⁻ᵀ(z) ∇_z log q_σ(z)`` (paper Eq. 4–5)."""

    def __call__(self, kernel: NoiseKernel, z: Tensor, sigma: Tensor | float) -> Tensor:
        return kernel.score_tangent(z, sigma)


class AutogradScore(ScoreTarget, name="autograd"):
    """``∂/∂τ log p_σ(Exp(z)·Exp(τ) | I)`` at ``τ = 0`` by autograd (supplement Eq. 18).

    The kernels are left-invariant, so the mean is taken as the identity without loss of
    generality. Costs one ``exp``, one ``rplus``, one ``log`` and a backward pass.
    """

    def __call__(self, kernel: NoiseKernel, z: Tensor, sigma: Tensor | float) -> Tensor:
        group = kernel.group
        with torch.enable_grad():
            tau = torch.zeros_like(z, requires_grad=True)
            x_noisy = group.rplus(group.exp(z.detach()), tau)
            mean = group.identity(z.shape[:-1], dtype=z.dtype, device=z.device)
            sig = sigma.detach() if isinstance(sigma, Tensor) else sigma
            lp = kernel.log_prob(x_noisy, mean, sig)
            (grad,) = torch.autograd.grad(lp.sum(), tau)
        return grad


def stein_score(
    group: LieGroup | str,
    z: Tensor,
    sigma: Tensor | float,
    method: str = "surrogate",
    *,
    kernel: NoiseKernel | None = None,
) -> Tensor:
    """The Stein score at ``X̃ = X · Exp(z)`` of the kernel ``p_σ(· | X)``, ``(*b, dim)``.

    Args:
        group: the Lie group (instance or registered name).
        z: tangent perturbation ``(*b, dim)``; for ``closed_form``/``autograd`` the principal one,
            ``Log(X⁻¹ X̃)``, since the density (paper Eq. 3) is written in those coordinates.
        sigma: noise level, broadcastable to ``z.shape[:-1]``.
        method: ``surrogate`` (Eq. 12), ``closed_form`` (Eq. 5) or ``autograd`` (Eq. 18); any name
            in ``ScoreTarget.registry``.
        kernel: the perturbation kernel (default: ``ConcentratedGaussian(group)``, Σ = σ²I).
    """
    group = get_group(group) if isinstance(group, str) else group
    if kernel is None:
        kernel = ConcentratedGaussian(group)
    elif kernel.group != group and type(kernel.group) is not type(group):
        raise ValueError(f"stein_score: kernel is on {kernel.group.name!r} but group is {group.name!r}")
    target = ScoreTarget.lookup(method)()
    return target(kernel, z, sigma)
