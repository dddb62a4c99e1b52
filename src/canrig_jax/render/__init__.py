"""Figures (matplotlib: per-vertex scalar maps) and differentiable rasterisers in JAX
(cameras, silhouettes, depth, Lambert shading, interpolated attributes, 2D displacement):
a soft one (``rasterise``, SoftRas-style) and a fast hard one with differentiable
interpolation and antialiased silhouettes (``rasterise_hard`` + ``interpolate`` +
``antialias``, nvdiffrast-style).

Also importable here but not in ``__all__`` (for the other subpackages): ``project_points``,
``ray_cast`` (a NumPy ray caster, the rasterisers' independent check),
``screen_displacement``."""

from ._antialias import antialias, silhouette
from ._camera import Camera, look_at, orbit_cameras
from ._camera import project_points as project_points
from ._camera import screen_displacement as screen_displacement
from ._hard import interpolate, rasterise_hard
from ._mesh_plot import plot_vertex_scalar, save_figure
from ._raster import RasterSettings, Rendering, displacement_field, lambert_image, rasterise
from ._reference import ray_cast as ray_cast

__all__ = [
    "Camera",
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
    "save_figure",
    "silhouette",
]
