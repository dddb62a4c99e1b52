"""Figures (matplotlib: per-vertex scalar maps) and a differentiable soft rasteriser in JAX
(cameras, silhouettes, depth, Lambert shading, interpolated attributes, 2D displacement)."""

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

__all__ = [
    "DEFAULT_LIGHTS",
    "PROJECTIONS",
    "Camera",
    "RasterSettings",
    "Rendering",
    "camera_depth",
    "check_camera",
    "displacement_field",
    "lambert_image",
    "look_at",
    "orbit_cameras",
    "plot_vertex_scalar",
    "project_points",
    "rasterise",
    "save_figure",
    "screen_displacement",
    "stack_cameras",
    "vertex_normals",
]
