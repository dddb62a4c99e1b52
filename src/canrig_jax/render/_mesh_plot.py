"""Orthographic mesh rendering with matplotlib: a per-vertex scalar (e.g. error in mm) as
colour, modulated by Lambert shading, triangles painted back to front."""

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from jaxtyping import ArrayLike, Float, Int  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.cm import ScalarMappable  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402


def plot_vertex_scalar(
    ax: Axes,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    values: Float[ArrayLike, " V"],
    *,
    vmin: float = 0.0,
    vmax: float = 5.0,
    cmap: str = "inferno",
    view: str = "front",
    title: str | None = None,
) -> ScalarMappable:
    """Draw ``values`` (V,) on the mesh seen from the front (+z towards the viewer) or the
    side (+x). Returns the ScalarMappable for a colour bar."""
    vertices = np.asarray(vertices, np.float64)
    if view == "side":
        vertices = vertices[:, [2, 1, 0]] * np.array([-1.0, 1.0, 1.0])
    elif view != "front":
        raise ValueError(f"view: expected 'front' or 'side', got {view!r}")
    faces = np.asarray(faces)
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
    visible = normal[:, 2] > 0
    order = np.argsort(tri[visible, :, 2].mean(axis=1))
    face_value = np.asarray(values, np.float64)[faces].mean(axis=1)[visible][order]
    mapper = ScalarMappable(norm=Normalize(vmin, vmax), cmap=cmap)
    shade = (0.35 + 0.65 * normal[visible, 2][order])[:, None]
    colours = mapper.to_rgba(face_value)
    colours[:, :3] *= shade
    ax.add_collection(
        PolyCollection(
            list(tri[visible][order][:, :, :2]),
            facecolors=colours,
            edgecolors=colours,
            linewidths=0.3,
        )
    )
    ax.set_xlim(vertices[:, 0].min(), vertices[:, 0].max())
    ax.set_ylim(vertices[:, 1].min(), vertices[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")
    if title:
        ax.set_title(title, fontsize=9)
    return mapper


def save_figure(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> None:
    """Save a figure atomically (PNG) and close it."""
    from .._io import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
