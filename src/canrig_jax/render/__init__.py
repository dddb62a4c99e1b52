"""Figures (matplotlib: per-vertex scalar maps) and differentiable rasterisers in JAX
(cameras, silhouettes, depth, Lambert shading, interpolated attributes, 2D displacement):
a soft one (``rasterise``, SoftRas-style) and a fast hard one with differentiable
interpolation and antialiased silhouettes (``rasterise_hard`` + ``interpolate`` +
``antialias``, nvdiffrast-style), and a NumPy ray caster (``ray_cast``) to check them.

Also importable here but not in ``__all__`` (for the other subpackages): ``project_points``,
``screen_displacement``."""

from ._antialias import antialias, silhouette
from ._camera import Camera, look_at, orbit_cameras, stack_cameras
from ._camera import project_points as project_points
from ._camera import screen_displacement as screen_displacement
from ._hard import Fragments, Interpolation, interpolate, rasterise_hard
from ._mesh_plot import plot_vertex_scalar, save_figure
from ._raster import RasterSettings, Rendering, displacement_field, lambert_image, rasterise
from ._reference import ray_cast

__all__ = [
    "Camera",
    "Fragments",
    "Interpolation",
    "RasterSettings",
    "Rendering",
    "antialias",
    "displacement_field",
    "interpolate",
    "lambert_image",
    "look_at",
    "orbit_cameras",
    "plot_vertex_scalar",
    "rasterise",
    "rasterise_hard",
    "ray_cast",
    "save_figure",
    "silhouette",
    "stack_cameras",
]
