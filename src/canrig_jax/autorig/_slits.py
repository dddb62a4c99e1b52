"""The sides of a face's slits: upper and lower lip, upper and lower lid of each eye.

A closed mouth puts the upper lip's inner surface a fraction of a millimetre from the lower
lip's; a closest-point correspondence (``mesh.closest_point_correspondence``) then lands
points of one lip on the other, and every transferred shape pulls the upper lip down with
the jaw and folds the mouth. The lids meet at the eye corners the same way. ``slit_sides``
labels the vertices around each slit by the side they are on, from the face's own
Multi-PIE landmarks and distances along the surface (``mesh.edge_graph``: the upper lip
reaches the lower lip only around the mouth corner or through the mouth), so the
correspondence can be told never to cross a slit (``source_sides=``, ``target_sides=``).
"""

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ..mesh import edge_graph, weighted_geodesic_distance

SLITS: dict[str, tuple[tuple[int, ...], tuple[int, ...], tuple[int, int]]] = {
    "mouth": ((50, 51, 52), (56, 57, 58), (48, 54)),
    "right_eye": ((37, 38), (40, 41), (36, 39)),
    "left_eye": ((43, 44), (46, 47), (42, 45)),
}
"""Slit -> (upper-side landmarks, lower-side landmarks, the two corners), 0-based indices
of the Multi-PIE 68 (the outer lip for the mouth, clear of the slit; the lid margins for
the eyes, open in a neutral)."""

SLIT_REACH = 0.5
"""Vertices within this many slit widths (corner to corner) of the segment between the
corners (in 3D) are labelled; the rest may be reached from either side (-1)."""


SLIT_SEPARATION = 0.5
"""A slit is labelled only when, along the surface, its two sides' landmarks are at least
this many slit widths apart (around a corner): on a mesh too coarse to part the lips (a
landmark on the wrong lip, both lips on one vertex) the slit is left unlabelled (-1)."""


def slit_sides(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    landmarks: Int[ArrayLike, " L"],
) -> Int[np.ndarray, " V"]:
    """(V,) int64 side of every vertex: 2 i for the upper and 2 i + 1 for the lower side of
    slit i of ``SLITS`` (mouth, right eye, left eye), -1 elsewhere. A vertex within
    ``SLIT_REACH`` slit widths of the segment between the slit's corners takes the side
    whose landmarks are nearer along the surface (-1 when neither is reached: a separate
    part such as an eyeball), and a slit whose sides the mesh does not part
    (``SLIT_SEPARATION``) is left at -1. Units: any (distances are relative to the slit)."""
    vertices = np.asarray(vertices, np.float64)
    landmarks = np.asarray(landmarks, np.int64)
    if landmarks.shape != (68,):
        raise ValueError(f"landmarks: expected the 68 Multi-PIE vertices, got {landmarks.shape}")
    graph = edge_graph(vertices, faces)
    sides = np.full(len(vertices), -1, np.int64)
    for i, (upper, lower, corners) in enumerate(SLITS.values()):
        a, b = vertices[landmarks[list(corners)]]
        width = float(np.linalg.norm(b - a))
        if not width > 0:
            continue
        along = np.clip((vertices - a) @ (b - a) / width**2, 0.0, 1.0)
        off = np.linalg.norm(vertices - (a + along[:, None] * (b - a)), axis=1)
        near = np.flatnonzero(off < SLIT_REACH * width)
        up, down = (
            weighted_geodesic_distance(graph, landmarks[list(seeds)], limit=8.0 * width).min(0)
            for seeds in (upper, lower)
        )
        if up[landmarks[list(lower)]].min() < SLIT_SEPARATION * width:
            continue  # the mesh does not part the two sides here: nothing to keep apart
        up, down = up[near], down[near]
        reached = np.isfinite(np.minimum(up, down))
        sides[near[reached]] = np.where(up[reached] <= down[reached], 2 * i, 2 * i + 1)
    return sides
