"""The diffusion contracts, run over every registered kernel, score target, schedule and sampler.

A new subclass (``class MyKernel(NoiseKernel, name="mine")``) is picked up from the registry and
checked automatically; the checks live in ``posediff.testing.diffusion`` for out-of-tree code.
"""

import functools

import pytest
import torch

from posediff.diffusion import NoiseKernel, NoiseSchedule, Sampler, ScoreTarget
from posediff.lie import LieGroup
from posediff.testing.diffusion import (
    KERNEL_CHECKS,
    SAMPLER_CHECKS,
    SCHEDULE_CHECKS,
    SCORE_TARGET_CHECKS,
    kernel_contract,
    kernel_groups,
    sampler_contract,
)

KERNEL_CASES = [(k, g) for k in sorted(NoiseKernel.registry) for g in kernel_groups(NoiseKernel.registry[k])]


@pytest.mark.parametrize("check", list(KERNEL_CHECKS))
@pytest.mark.parametrize(("kernel", "group"), KERNEL_CASES)
def test_kernel_contract(kernel: str, group: str, check: str, device: torch.device) -> None:
    KERNEL_CHECKS[check](NoiseKernel.registry[kernel](group), device)


@pytest.mark.parametrize("check", list(KERNEL_CHECKS))
def test_kernel_contract_with_component_scales(check: str, device: torch.device) -> None:
    for name in sorted(NoiseKernel.registry):
        KERNEL_CHECKS[check](
            NoiseKernel.registry[name]("se3", translation_scale=2.0, rotation_scale=0.5), device
        )


@pytest.mark.parametrize("check", list(SCORE_TARGET_CHECKS))
@pytest.mark.parametrize("group", ["so3", "r3so3", "se3"])
@pytest.mark.parametrize("target", sorted(ScoreTarget.registry))
def test_score_target_contract(target: str, group: str, check: str, device: torch.device) -> None:
    SCORE_TARGET_CHECKS[check](ScoreTarget.registry[target](), LieGroup.registry[group](), device)


@pytest.mark.parametrize("check", list(SCHEDULE_CHECKS))
@pytest.mark.parametrize("schedule", sorted(NoiseSchedule.registry))
def test_schedule_contract(schedule: str, check: str) -> None:
    SCHEDULE_CHECKS[check](NoiseSchedule.registry[schedule]())


@pytest.mark.parametrize("check", list(SAMPLER_CHECKS))
@pytest.mark.parametrize("sampler", sorted(Sampler.registry))
def test_sampler_contract(sampler: str, check: str, device: torch.device) -> None:
    SAMPLER_CHECKS[check](Sampler.registry[sampler], device)


def test_contracts_cover_the_builtins() -> None:
    assert {"gaussian", "igso3"} <= set(NoiseKernel.registry)
    assert {"surrogate", "closed_form", "autograd"} <= set(ScoreTarget.registry)
    assert {"linear", "power", "loglinear"} <= set(NoiseSchedule.registry)
    assert {"random_walk", "ancestral", "few_step", "heun", "crouch_grossman", "rkmk"} <= set(
        Sampler.registry
    )


def test_sampler_contract_catches_a_broken_sampler() -> None:
    """The contract can fail: a sampler that stops denoising below σ = 0.05 misses the point."""
    from posediff.diffusion import FewStepSampler

    class Lazy(FewStepSampler):  # not registered
        def step(self, denoise_fn, x, sigma_t, sigma_p, cond, generator):  # noqa: ANN001, ANN201
            return x if sigma_t < 0.05 else super().step(denoise_fn, x, sigma_t, sigma_p, cond, generator)

    with pytest.raises(AssertionError, match="point_mass"):
        sampler_contract(functools.partial(Lazy), checks=["point_mass"])


def test_kernel_contract_catches_a_wrong_score() -> None:
    from posediff.diffusion import ConcentratedGaussian

    class Wrong(ConcentratedGaussian):  # not registered
        def _grad_log_prob_tangent(self, z, sigma_c):  # noqa: ANN001, ANN202
            return -1.1 * z / sigma_c**2

    with pytest.raises(AssertionError, match="score_matches_autograd"):
        kernel_contract(Wrong("so3"), checks=["score_matches_autograd"])


def test_five_nfe_check_catches_a_one_jump_sampler() -> None:
    """The 5-NFE check can fail: one clean-pose jump from the prior (the posterior mean at σ_max) lands
    between the modes of the weighted mixture."""
    from posediff.diffusion import FewStepSampler

    class OneJump(FewStepSampler):  # not registered
        def steps_for_nfe(self, nfe: int) -> int:
            return 1

    with pytest.raises(AssertionError, match="five_nfe: weighted mixture"):
        sampler_contract(OneJump, checks=["five_nfe"])
