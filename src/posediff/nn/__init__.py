"""Neural networks for score-based pose diffusion: the image-free denoiser and its parts.

* :class:`SinusoidalEmbedding`: per-scalar sinusoidal embedding of poses and noise levels.
* :class:`ConditionedBlock` (registry family "conditioned block"): :class:`FourierBlock` ("fourier",
  paper Eq. 13) and :class:`ScaleBiasBlock` ("scale_bias", FiLM).
* :class:`MLPDenoiser`: the reference head, tangent vector + noise level + condition → tangent vector.
* :class:`ResNetEncoder`: image → condition vector (torchvision ResNet + the paper's feature head).
* :class:`PoseEncoder`: image → :class:`Encoding` (feature + an anchor pose from a pose head;
  optionally locate-then-crop), for the anchored denoiser and the regression baselines.
* :func:`pose_input_dim` / :func:`pose_features`: what the denoiser sees of a pose.
"""

from .blocks import ACTIVATIONS, ConditionedBlock, FourierBlock, LecunLinear, ScaleBiasBlock, make_activation
from .denoiser import MLPDenoiser
from .embedding import SinusoidalEmbedding
from .encoder import ResNetEncoder
from .pose_encoder import CropBoxError, Encoding, PoseEncoder, ray_rotation, rotation_from_6d
from .pose_input import POSE_INPUTS, pose_features, pose_input_dim

__all__ = [
    "ACTIVATIONS",
    "ConditionedBlock",
    "CropBoxError",
    "Encoding",
    "FourierBlock",
    "LecunLinear",
    "MLPDenoiser",
    "POSE_INPUTS",
    "PoseEncoder",
    "ResNetEncoder",
    "ScaleBiasBlock",
    "SinusoidalEmbedding",
    "make_activation",
    "pose_features",
    "pose_input_dim",
    "ray_rotation",
    "rotation_from_6d",
]
