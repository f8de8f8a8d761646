"""Moved to :mod:`posediff.evaluation.predict` (the pictures' drawing to :mod:`posediff.viz.prediction`,
over plain arrays); these names stay importable from here (CHANGELOG, 0.2.0)."""

from .evaluation.predict import (
    MAX_IMAGE_PIXELS,
    ImageError,
    Prediction,
    decode_prediction,
    figure_so3,
    figure_trajectory,
    figure_translations,
    image_tensor,
    load_image,
    overlay,
    predict,
    read_image,
    save_prediction,
)

__all__ = [
    "MAX_IMAGE_PIXELS",
    "ImageError",
    "Prediction",
    "decode_prediction",
    "figure_so3",
    "figure_trajectory",
    "figure_translations",
    "image_tensor",
    "load_image",
    "overlay",
    "predict",
    "read_image",
    "save_prediction",
]
