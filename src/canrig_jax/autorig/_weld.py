"""Clumps of a head's vertices that move as one.

Sculptors leave clumps of vertices a fraction of a millimetre apart where the mouth's and the
lids' edge loops meet (the mouth corners, the lip middle, the outer eye corners). An artist's
shape moves such a clump as one; a generated shape (closest points on a template, a network's
per-vertex output) gives its vertices deltas that differ by more than the clump's own size,
and its tiny triangles turn inside out under motion. ``weld`` replaces each clump's deltas
by their mean, in every pose, so a clump translates as one and its triangles keep their
facing.

A clump: skin vertices joined by skin edges shorter than ``WELD_TAU`` times the head's median
skin edge (connected components, ``scipy.sparse.csgraph``).
"""

import numpy as np
import scipy.sparse as sp
from jaxtyping import ArrayLike, Bool, Float, Int
from scipy.sparse.csgraph import connected_components

from ..mesh import mesh_edges

WELD_TAU = 0.2
"""Edges shorter than this fraction of the head's median skin edge join a clump (0 leaves
every vertex on its own: the step off). Chosen from {0.1, 0.2, 0.3} by a rule written
before it was measured, on validation heads only (``experiments/results/any_head_motion/``
``RULE.md``, "Welding micro-clusters"; ``steps_weld.md``)."""


def clumps(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    skin: Bool[ArrayLike, " V"],
    tau: float = WELD_TAU,
) -> Int[np.ndarray, " V"]:
    """(V,) int: a clump label per vertex (vertices of one clump share it; a vertex on its
    own has a label no other vertex has). Only edges of triangles wholly on the ``skin``
    join clumps; lengths in the vertices' units, relative to the skin's median edge."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    skin = np.asarray(skin, bool)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {v.shape}")
    if skin.shape != (len(v),):
        raise ValueError(f"skin: expected shape ({len(v)},), got {skin.shape}")
    if not 0.0 <= tau < 1.0:
        raise ValueError(f"tau: expected a fraction of the median edge in [0, 1), got {tau}")
    f = f[skin[f].all(axis=1)]
    edges = mesh_edges(f)
    if tau == 0.0 or len(edges) == 0:
        return np.arange(len(v))
    length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    short = edges[length < tau * np.median(length)]
    graph = sp.coo_matrix((np.ones(len(short)), (short[:, 0], short[:, 1])), (len(v), len(v)))
    return connected_components(graph, directed=False)[1]


def weld(
    displacements: Float[ArrayLike, "P V 3"], labels: Int[ArrayLike, " V"]
) -> Float[np.ndarray, "P V 3"]:
    """(P, V, 3): each clump's displacements (same ``labels``, from ``clumps``) replaced by
    their mean in every pose; vertices on their own unchanged (the same array values)."""
    d = np.asarray(displacements)
    labels = np.asarray(labels)
    if d.ndim != 3 or d.shape[1:] != (len(labels), 3):
        raise ValueError(f"displacements: expected shape (P, {len(labels)}, 3), got {d.shape}")
    _, index, size = np.unique(labels, return_inverse=True, return_counts=True)
    if size.max(initial=1) == 1:
        return d
    members = np.flatnonzero(size[index] > 1)
    groups = index[members]
    sums = np.zeros((d.shape[0], len(size), 3), np.float64)
    np.add.at(sums, (slice(None), groups), d[:, members].astype(np.float64))
    out = d.copy()
    out[:, members] = (sums[:, groups] / size[groups][None, :, None]).astype(d.dtype)
    return out
