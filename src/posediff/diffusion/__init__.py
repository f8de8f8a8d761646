"""Score-based diffusion on Lie groups: kernels, score targets, schedules, samplers, modes.

The pieces (paper §4; equation numbers follow the tex, see ``docs/conventions.md``):

* ``NoiseKernel`` registry — ``ConcentratedGaussian`` (Eq. 3) and ``IGSO3`` (Eq. 14–15);
* ``stein_score(group, z, sigma, method)`` — ``surrogate`` (Eq. 12), ``closed_form`` (Eq. 5),
  ``autograd`` (Eq. 18);
* ``NoiseSchedule`` registry — ``linear`` (paper), ``power`` (authors' code), ``loglinear``;
* ``Diffusion`` — kernel + schedule + target + output parameterisation + loss + prior;
* ``Sampler`` registry — ``random_walk`` (Eq. 7), ``ancestral`` (authors' code), ``few_step``,
  and the probability-flow ODE samplers ``heun``, ``crouch_grossman``, ``rkmk`` (``ode``);
* ``modes`` — cluster samples into weighted modes; ``log_likelihood`` — probability-flow ODE.
"""

from .flow import FlowEulerSampler as FlowEulerSampler
from .flow import FlowHeunSampler as FlowHeunSampler
from .flow import FlowOracle as FlowOracle
from .flow import FlowSampler as FlowSampler
from .igso3 import IGSO3 as IGSO3
from .kernels import ConcentratedGaussian as ConcentratedGaussian
from .kernels import NoiseKernel as NoiseKernel
from .likelihood import log_likelihood as log_likelihood
from .modes import Modes as Modes
from .modes import modes as modes
from .ode import CrouchGrossmanSampler as CrouchGrossmanSampler
from .ode import HeunSampler as HeunSampler
from .ode import ProbabilityFlowSampler as ProbabilityFlowSampler
from .ode import RKMKSampler as RKMKSampler
from .oracle import MixtureOracle as MixtureOracle
from .process import Diffusion as Diffusion
from .process import NoisyBatch as NoisyBatch
from .samplers import AncestralSampler as AncestralSampler
from .samplers import FewStepSampler as FewStepSampler
from .samplers import GeodesicRandomWalk as GeodesicRandomWalk
from .samplers import Sampler as Sampler
from .schedules import LinearSchedule as LinearSchedule
from .schedules import LogLinearSchedule as LogLinearSchedule
from .schedules import NoiseSchedule as NoiseSchedule
from .schedules import PowerSchedule as PowerSchedule
from .score import ScoreTarget as ScoreTarget
from .score import stein_score as stein_score

__all__ = [
    "NoiseKernel",
    "ConcentratedGaussian",
    "IGSO3",
    "ScoreTarget",
    "stein_score",
    "NoiseSchedule",
    "LinearSchedule",
    "LogLinearSchedule",
    "PowerSchedule",
    "Diffusion",
    "NoisyBatch",
    "Sampler",
    "GeodesicRandomWalk",
    "AncestralSampler",
    "FewStepSampler",
    "ProbabilityFlowSampler",
    "HeunSampler",
    "CrouchGrossmanSampler",
    "RKMKSampler",
    "MixtureOracle",
    "FlowSampler",
    "FlowEulerSampler",
    "FlowHeunSampler",
    "FlowOracle",
    "log_likelihood",
    "Modes",
    "modes",
]
