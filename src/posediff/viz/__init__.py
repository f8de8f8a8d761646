"""``posediff.viz``: headless matplotlib plots of pose distributions (see :mod:`posediff.viz.mollweide`)."""

from .mollweide import plot_so3, plot_translations, rotation_to_mollweide, save_figure

__all__ = ["plot_so3", "plot_translations", "rotation_to_mollweide", "save_figure"]
