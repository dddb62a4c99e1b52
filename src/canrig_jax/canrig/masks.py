"""Geodesic influence masks of CANRig handles (section 3.1 and appendix A).

Distances are shortest paths on the mesh's edge graph, each edge weighted by its 3D length
(``scipy.sparse.csgraph.dijkstra``), so a handle on the upper lip reaches the lower lip only
around the mouth corner, never across the mouth gap. Appendix A's correlation prior scales
each edge by ``1 - |corr(v_i, v_j)|``: vertices that move together are close.

The mask of handle h on vertex v is (arrays are laid out vertices x handles, (V, H), the
layout the attention consumes)

    M_{h,v} = 0.5 (1 - tanh(gamma_h (d(h, v) - r_h)))

with radius r_h and falloff gamma_h per handle. ``influence_mask`` is a jnp function of
arrays, so radii and falloffs change per call without recompiling.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float
from scipy.sparse.csgraph import dijkstra

CLAMP = 1e-2
"""Influences below this are clamped to exactly 0 (section 3.2)."""

MIN_EDGE_FACTOR = 1e-3
"""Floor of the correlation-prior edge factor: csgraph drops zero-weight edges."""


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges (i < j) of a triangle mesh."""
    faces = np.asarray(faces, np.int64)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs = np.sort(pairs, axis=1)
    return np.unique(pairs, axis=0)


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("vertices: contains non-finite values")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0:
        raise ValueError(f"faces: expected shape (F, 3) with F > 0, got {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"faces: indices must lie in [0, {len(vertices)})")
    return vertices, faces


def edge_graph(
    vertices: np.ndarray, faces: np.ndarray, edge_factor: np.ndarray | None = None
) -> sp.csr_matrix:
    """(V, V) symmetric sparse graph, edge weights = 3D edge length (times ``edge_factor``,
    one factor per edge of ``mesh_edges(faces)``, if given)."""
    vertices, faces = _check_mesh(vertices, faces)
    edges = mesh_edges(faces)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    if edge_factor is not None:
        edge_factor = np.asarray(edge_factor, np.float64)
        if edge_factor.shape != (len(edges),):
            raise ValueError(
                f"edge_factor: expected shape ({len(edges)},), got {edge_factor.shape}"
            )
        length = length * edge_factor
    length = np.maximum(length, 1e-12)  # csgraph treats stored zeros as missing edges
    n = len(vertices)
    graph = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n))
    return (graph + graph.T).tocsr()


def correlation_edge_factor(faces: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """(E,) appendix A's prior ``1 - |corr(v_i, v_j)|`` per edge of ``mesh_edges(faces)``.

    ``shapes`` (N, V, 3) are training shapes; the correlation of two vertices is the Pearson
    correlation of their displacement from the mean shape, pooled over the N shapes and 3
    coordinates. Floored at ``MIN_EDGE_FACTOR`` so every edge keeps a positive weight.
    """
    shapes = np.asarray(shapes, np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or shapes.shape[0] < 2:
        raise ValueError(f"shapes: expected shape (N >= 2, V, 3), got {shapes.shape}")
    edges = mesh_edges(faces)
    if edges.max() >= shapes.shape[1]:
        raise ValueError("faces: indices exceed the vertex count of shapes")
    centred = shapes - shapes.mean(axis=0)
    # (V, 3N): each vertex's displacement trajectory, centred per coordinate
    signal = centred.transpose(1, 0, 2).reshape(shapes.shape[1], -1)
    norm = np.linalg.norm(signal, axis=1)
    dot = np.einsum("ek,ek->e", signal[edges[:, 0]], signal[edges[:, 1]])
    denom = norm[edges[:, 0]] * norm[edges[:, 1]]
    corr = np.where(denom > 0, dot / np.where(denom > 0, denom, 1.0), 0.0)
    return np.maximum(1.0 - np.abs(corr), MIN_EDGE_FACTOR)


def weighted_geodesic_distance(
    graph: sp.csr_matrix, sources: ArrayLike, *, limit: float = np.inf
) -> np.ndarray:
    """(H, V) float32 shortest-path distance from each source vertex to every vertex.

    Vertices farther than ``limit`` (or unreachable) get ``inf``; a finite limit makes many
    handles on a large mesh cheap, and any mask is then 0 there for radii well below it.
    """
    sources = np.asarray(sources)
    n = graph.shape[0]
    if sources.ndim != 1 or sources.size == 0:
        raise ValueError(f"sources: expected a non-empty 1-D index array, got {sources.shape}")
    if not np.issubdtype(sources.dtype, np.integer):
        raise ValueError(f"sources: expected integer vertex indices, got {sources.dtype}")
    if sources.min() < 0 or sources.max() >= n:
        raise ValueError(
            f"sources: indices must lie in [0, {n}), got {sources.min()}..{sources.max()}"
        )
    if not limit > 0:
        raise ValueError(f"limit: expected > 0, got {limit}")
    return dijkstra(graph, directed=False, indices=sources, limit=limit).astype(np.float32)


def influence_mask(
    distance: Float[ArrayLike, "V H"],
    radius: Float[ArrayLike, " H"],
    falloff: Float[ArrayLike, " H"],
    clamp: float = 0.0,
) -> Float[Array, "V H"]:
    """Influence M_{h,v} = 0.5 (1 - tanh(falloff_h (d_{h,v} - radius_h))) of each handle
    (last axis) on each vertex; values below ``clamp`` become exactly 0, infinite distances
    give 0. jit/vmap/grad-safe."""
    distance = jnp.asarray(distance)
    radius = jnp.asarray(radius)
    falloff = jnp.asarray(falloff)
    finite = jnp.isfinite(distance)
    scaled = falloff * (jnp.where(finite, distance, 0.0) - radius)
    mask = jnp.where(finite, 0.5 * (1.0 - jnp.tanh(scaled)), 0.0)
    if clamp > 0.0:
        mask = jnp.where(mask < clamp, 0.0, mask)
    return mask


def check_handle_parameters(radius, falloff, n_handles: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate radius and falloff (scalars or (H,)) and broadcast them to (H,) float32."""
    out = []
    for name, value in (("radius", radius), ("falloff", falloff)):
        arr = np.asarray(value, np.float32)
        if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n_handles):
            raise ValueError(f"{name}: expected a scalar or shape ({n_handles},), got {arr.shape}")
        if not np.all(np.isfinite(arr)) or not np.all(arr > 0):
            raise ValueError(f"{name}: expected finite values > 0, got min {arr.min()}")
        out.append(np.broadcast_to(arr, (n_handles,)).copy())
    return out[0], out[1]
