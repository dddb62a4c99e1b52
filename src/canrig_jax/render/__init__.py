"""Figures (matplotlib: per-vertex scalar maps) and differentiable rasterisers in JAX
(cameras, silhouettes, depth, Lambert shading, interpolated attributes, 2D displacement):
a soft one (``rasterise``, SoftRas-style) and a fast hard one with differentiable
interpolation and antialiased silhouettes (``rasterise_hard`` + ``interpolate`` +
``antialias``, nvdiffrast-style), and a NumPy ray caster (``ray_cast``) to check them."""

from ._antialias import antialias, silhouette
from ._camera import (
    PROJECTIONS,
    Camera,
    camera_depth,
    check_camera,
    look_at,
    orbit_cameras,
    project_points,
    screen_displacement,
    stack_cameras,
)
from ._hard import Fragments, Interpolation, interpolate, rasterise_hard
from ._mesh_plot import plot_vertex_scalar, save_figure
from ._raster import (
    DEFAULT_LIGHTS,
    RasterSettings,
    Rendering,
    displacement_field,
    lambert_image,
    rasterise,
    vertex_normals,
)
from ._reference import ray_cast

__all__ = [
    "antialias",
    "DEFAULT_LIGHTS",
    "PROJECTIONS",
    "Camera",
    "Fragments",
    "Interpolation",
    "RasterSettings",
    "Rendering",
    "camera_depth",
    "check_camera",
    "displacement_field",
    "lambert_image",
    "interpolate",
    "look_at",
    "orbit_cameras",
    "plot_vertex_scalar",
    "project_points",
    "rasterise",
    "rasterise_hard",
    "ray_cast",
    "save_figure",
    "screen_displacement",
    "silhouette",
    "stack_cameras",
    "vertex_normals",
]
