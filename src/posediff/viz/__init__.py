"""``posediff.viz``: headless matplotlib plots of pose distributions (:mod:`posediff.viz.mollweide`)
and the pictures of a prediction (:mod:`posediff.viz.prediction`), over plain arrays."""

from .mollweide import plot_so3, plot_translations, rotation_to_mollweide, save_figure
from .prediction import figure_so3, figure_trajectory, figure_translations, mesh_edges, overlay

__all__ = [
    "figure_so3",
    "figure_trajectory",
    "figure_translations",
    "mesh_edges",
    "overlay",
    "plot_so3",
    "plot_translations",
    "rotation_to_mollweide",
    "save_figure",
]
