"""A take of meshes with its error as vertex colour: an animated glb for ``canrig view``.

An experiment that compares meshes frame by frame (a solved inverse rig against its targets,
an edited rig against the sculpt, a neural rig's output against the intended shape) has, per
frame, a mesh and a per-vertex error. ``export_error_glb`` bakes the meshes as one morph target
per frame (keyed one at a time, so at each key time the glb shows that frame's mesh exactly)
and colours every vertex by its mean error over the frames (``error_colors``: white at 0, red
at ``vmax_mm`` and above), so a user can scrub the take and turn the head around the worst
vertex. ``save_error_legend`` draws the colour scale as a small PNG to go beside it.
"""

import dataclasses
import os
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from .._checks import check_finite, check_real
from ..rig import BlendshapeRig, export_animated_gltf
from ._colors import error_colors


@dataclasses.dataclass(frozen=True)
class ErrorGlb:
    """What ``export_error_glb`` wrote (its docstring lists the fields)."""

    path: Path
    vertex_error_mm: Float[np.ndarray, " V"]
    """(V,) the coloured error: each vertex's mean over the frames (mm)."""
    vmax_mm: float
    """The error drawn pure red (and everything above it)."""
    worst_vertex: int
    """The vertex with the largest mean error (within ``region`` when given)."""
    worst_frame: int
    """The frame where the worst vertex's error is largest."""
    colors: Float[np.ndarray, "V 3"]
    """(V, 3) the linear RGB written as ``COLOR_0``."""
    times: Float[np.ndarray, " T"]
    """(T,) key time of each frame (s)."""


def _checked_take(meshes, error_mm, region, neutral):
    """``export_error_glb``'s arrays, checked (ValueError naming the argument), with the
    defaults of ``region`` (every vertex) and ``neutral`` (the first frame) filled in."""
    meshes = np.asarray(meshes)
    if meshes.ndim != 3 or meshes.shape[2] != 3 or meshes.shape[0] < 1 or meshes.shape[1] < 3:
        raise ValueError(f"meshes: expected (T, V, 3) with T >= 1 frames, got {meshes.shape}")
    check_real("meshes", meshes)
    check_finite("meshes", meshes)
    t, v = meshes.shape[:2]
    error_mm = np.asarray(error_mm)
    if error_mm.shape != (t, v):
        raise ValueError(
            f"error_mm: expected shape ({t}, {v}) (frames, vertices), got {error_mm.shape}"
        )
    check_real("error_mm", error_mm)
    check_finite("error_mm", error_mm)
    if error_mm.min() < 0:
        raise ValueError(f"error_mm: expected non-negative errors, got {error_mm.min()}")
    if region is None:
        region = np.ones(v, bool)
    region = np.asarray(region)
    if region.shape != (v,) or region.dtype != bool or not region.any():
        raise ValueError(f"region: expected a ({v},) bool mask with a True vertex")
    if neutral is None:
        neutral = meshes[0]
    neutral = np.asarray(neutral)
    if neutral.shape != (v, 3):
        raise ValueError(f"neutral: expected shape ({v}, 3), got {neutral.shape}")
    check_finite("neutral", neutral)
    return meshes, error_mm, region, neutral


def export_error_glb(
    path: str | os.PathLike,
    meshes: Float[ArrayLike, "T V 3"],
    faces: Int[ArrayLike, "F 3"],
    error_mm: Float[ArrayLike, "T V"],
    *,
    vmax_mm: float | None = None,
    region: Bool[ArrayLike, " V"] | None = None,
    times: Float[ArrayLike, " T"] | None = None,
    fps: float = 30.0,
    neutral: Float[ArrayLike, "V 3"] | None = None,
    units: str = "cm",
) -> ErrorGlb:
    """Write ``meshes`` as an animated glb coloured by ``error_mm`` (atomically).

    Args:
        path: the ``.glb`` to write.
        meshes: (T, V, 3) the mesh of each frame (rig units), finite.
        faces: (F, 3) triangles.
        error_mm: (T, V) non-negative per-frame, per-vertex error in mm; each vertex is
            coloured by its mean over the frames.
        vmax_mm: the error drawn pure red; default the 95th percentile of the coloured error
            (over ``region``).
        region: optional (V,) bool, the vertices that count for ``worst_vertex`` and the
            default ``vmax_mm`` (e.g. the skin, or the mouth); every vertex is coloured.
        times: (T,) strictly increasing key times (s); default ``arange(T) / fps``.
        fps: frames per second when ``times`` is not given.
        neutral: (V, 3) the morph targets' base (e.g. the rig's rest mesh, so a target's
            slider reads as that frame); default the first frame.
        units: the meshes' length unit (recorded in the file).

    Returns:
        An ``ErrorGlb``: the ``path`` written; ``vertex_error_mm`` (V,), the coloured error
        (each vertex's mean over the frames, mm); ``vmax_mm``, the error drawn pure red (and
        everything above it); ``worst_vertex``, the vertex with the largest mean error (within
        ``region`` when given) and ``worst_frame``, the frame where its error is largest;
        ``colors`` (V, 3), the linear RGB written as ``COLOR_0``; ``times`` (T,), the key time
        of each frame (s).

    Raises ValueError naming the argument for inconsistent shapes, non-finite values,
    negative errors, an empty region or a zero colour scale.
    """
    meshes, error_mm, region, neutral = _checked_take(meshes, error_mm, region, neutral)
    t, v = meshes.shape[:2]

    vertex_error = error_mm.mean(axis=0)
    if vmax_mm is None:
        vmax_mm = float(np.percentile(vertex_error[region], 95))
    colors = error_colors(vertex_error, vmax_mm)  # checks vmax_mm > 0
    worst = int(np.flatnonzero(region)[np.argmax(vertex_error[region])])
    take = BlendshapeRig(
        neutral.astype(np.float32),
        (meshes - neutral[None]).astype(np.float32),
        (),
        [f"frame {i:03d}" for i in range(t)],
        faces,
        units=units,
    )
    if times is None:
        times = np.arange(t, dtype=np.float64) / fps
    written = export_animated_gltf(
        take,
        np.eye(t, dtype=np.float32),
        path,
        fps=fps,
        times=times,
        name="error",
        vertex_colors=colors,
    )
    return ErrorGlb(
        path=written,
        vertex_error_mm=vertex_error,
        vmax_mm=float(vmax_mm),
        worst_vertex=worst,
        worst_frame=int(np.argmax(error_mm[:, worst])),
        colors=colors,
        times=np.asarray(times, np.float64),
    )


def save_error_legend(
    path: str | os.PathLike, vmax_mm: float, label: str = "mean error over the take (mm)"
) -> Path:
    """A colour bar of ``error_colors`` from 0 to ``vmax_mm`` (as the viewer shows it: the
    linear ``COLOR_0`` encoded to sRGB), written as a PNG (atomically)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, Normalize

    from ..render import save_figure  # matplotlib (Agg), imported only when drawing

    ramp = np.linspace(0.0, vmax_mm, 256)
    linear = error_colors(ramp, vmax_mm)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    fig, ax = plt.subplots(figsize=(4.0, 0.9))
    fig.subplots_adjust(left=0.05, right=0.95, bottom=0.55, top=0.9)
    mapper = plt.cm.ScalarMappable(Normalize(0.0, vmax_mm), ListedColormap(srgb))
    bar = fig.colorbar(mapper, cax=ax, orientation="horizontal")
    bar.set_label(f"{label}; red: >= {vmax_mm:.3g} mm", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    save_figure(fig, path, dpi=150)
    return Path(path)
