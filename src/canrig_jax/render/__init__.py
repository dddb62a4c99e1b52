"""Figures: per-vertex scalar maps on meshes (matplotlib, no GPU)."""

from ._mesh_plot import plot_vertex_scalar, save_figure

__all__ = ["plot_vertex_scalar", "save_figure"]
