"""Neural networks for score-based pose diffusion: the image-free denoiser and its parts.

* :class:`SinusoidalEmbedding`: per-scalar sinusoidal embedding of poses and noise levels.
* :class:`ConditionedBlock` (registry family "conditioned block"): :class:`FourierBlock` ("fourier",
  paper Eq. 13) and :class:`ScaleBiasBlock` ("scale_bias", FiLM).
* :class:`MLPDenoiser`: the reference head, tangent vector + noise level + condition → tangent vector.
* :class:`ResNetEncoder`: image → condition vector (torchvision ResNet + the paper's feature head).
"""

from .blocks import ACTIVATIONS, ConditionedBlock, FourierBlock, LecunLinear, ScaleBiasBlock, make_activation
from .denoiser import MLPDenoiser
from .embedding import SinusoidalEmbedding
from .encoder import ResNetEncoder

__all__ = [
    "ACTIVATIONS",
    "ConditionedBlock",
    "FourierBlock",
    "LecunLinear",
    "MLPDenoiser",
    "ResNetEncoder",
    "ScaleBiasBlock",
    "SinusoidalEmbedding",
    "make_activation",
]
