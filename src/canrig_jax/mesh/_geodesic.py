"""Graph geometry of a triangle mesh: edges, the edge-length graph, geodesic distances along
it, and farthest-point sampling.

Distances are shortest paths on the mesh's edge graph, each edge weighted by its 3D length
(times an optional per-edge factor; ``scipy.sparse.csgraph.dijkstra``), so a vertex on the
upper lip reaches the lower lip only around the mouth corner, never across the mouth gap.

A head is rarely one connected surface: teeth, gums, eyelashes and eye parts float beside the
skin, so no path along edges reaches them from a handle on the skin. ``bridged_edge_graph``
adds one directed "exit" edge from every vertex of every other component to its nearest
vertex (3D) of the main one: shortest paths lead out of a small part onto the skin, never
into one and out again, so no path between two skin vertices takes a shortcut through the
teeth across the mouth gap.

A part may also be reached from a chosen stretch of surface rather than the nearest one:
``attached_edge_graph`` adds a directed edge from every vertex of the given parts to its
nearest vertex (3D) of a target set (the mouth interior onto the face skin, so a tooth is
measured from the lips' inner surface, straight through the mouth cavity, rather than along
the socket wall), and removes the edges that lead into those parts from outside: paths leave
them, none enters, so distances between two vertices outside them are those of the graph
without them.
"""

from typing import Any

import numpy as np
import scipy.sparse as sp
from jaxtyping import ArrayLike, Bool, Float, Float32, Int
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import KDTree

from ._checks import check_mesh, check_vertices, sparse_shape

MIN_EDGE_LENGTH = 1e-12
"""csgraph treats stored zeros as missing edges: lengths are floored at this."""


def mesh_edges(faces: Int[ArrayLike, "F 3"]) -> Int[np.ndarray, "E 2"]:
    """(E, 2) unique undirected edges (i < j) of a triangle mesh."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3) triangles, got {faces.shape}")
    if faces.size and not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces: expected integer vertex indices, got dtype {faces.dtype}")
    faces = faces.astype(np.int64)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs = np.sort(pairs, axis=1)
    return np.unique(pairs, axis=0)


def edge_graph(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    edge_factor: Float[ArrayLike, " E"] | None = None,
) -> sp.csr_matrix:
    """(V, V) symmetric sparse graph, edge weights = 3D edge length (times ``edge_factor``,
    one positive factor per edge of ``mesh_edges(faces)``, if given)."""
    vertices, faces = check_mesh(vertices, faces)
    edges = mesh_edges(faces)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    if edge_factor is not None:
        edge_factor = np.asarray(edge_factor, np.float64)
        if edge_factor.shape != (len(edges),):
            raise ValueError(
                f"edge_factor: expected shape ({len(edges)},), got {edge_factor.shape}"
            )
        if not np.all(np.isfinite(edge_factor)) or np.any(edge_factor <= 0):
            raise ValueError("edge_factor: expected finite factors > 0")
        length = length * edge_factor
    length = np.maximum(length, MIN_EDGE_LENGTH)
    n = len(vertices)
    graph = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n))
    return (graph + graph.T).tocsr()


def bridged_edge_graph(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    edge_factor: Float[ArrayLike, " E"] | None = None,
) -> sp.csr_matrix:
    """``edge_graph`` plus a directed edge (weight: the 3D distance) from every vertex of every
    connected component but the largest to its nearest vertex of the largest.

    The result is not symmetric: distances from any vertex *to* the main component are finite
    (``weighted_geodesic_distance(graph, sources)`` with the sources anywhere and the targets
    on the main component; its transpose for paths from the main component into the small
    parts). Paths between two vertices of the main component never leave it. A mesh of one
    component gets the plain ``edge_graph``.
    """
    vertices, faces = check_mesh(vertices, faces)
    graph = edge_graph(vertices, faces, edge_factor)
    n_components, label = connected_components(graph, directed=False)
    if n_components == 1:
        return graph
    main = np.flatnonzero(label == np.argmax(np.bincount(label)))
    others = np.flatnonzero(label != label[main[0]])
    length, nearest = KDTree(vertices[main]).query(vertices[others])
    n = len(vertices)
    exits = sp.csr_matrix(
        (np.maximum(length, MIN_EDGE_LENGTH), (others, main[nearest])), shape=(n, n)
    )
    return (graph + exits).tocsr()


def attached_edge_graph(
    graph: sp.csr_matrix,
    vertices: Float[ArrayLike, "V 3"],
    attach: Bool[ArrayLike, " V"],
    onto: Bool[ArrayLike, " V"],
) -> sp.csr_matrix:
    """``graph`` (``edge_graph`` or ``bridged_edge_graph``, (V, V)) with the vertices of
    ``attach`` (a (V,) boolean mask) made one-way exits onto ``onto`` (a (V,) boolean mask,
    disjoint from ``attach``).

    Every edge from a vertex outside ``attach`` into it is removed, its edges within and out
    of it are kept, and each of its vertices gets a directed edge (weight: the 3D distance) to
    its nearest vertex of ``onto``. Distances from a vertex of ``attach`` to the rest are
    finite (if ``onto`` is reachable) and at most the straight line to ``onto`` plus the path
    on from there; no path between two vertices outside ``attach`` passes through it, so
    their distances are those of ``graph`` with ``attach`` deleted (unchanged wherever no
    shortest path ran through it). As ``bridged_edge_graph``: sources anywhere, targets
    outside ``attach``; the transpose for paths from outside into it.
    """
    graph = _check_graph(graph).tocsr()
    vertices = check_vertices(vertices)
    n = len(vertices)
    if graph.shape != (n, n):
        raise ValueError(f"graph: expected shape ({n}, {n}), got {graph.shape}")
    masks: list[np.ndarray] = []
    for name, value in (("attach", attach), ("onto", onto)):
        value = np.asarray(value)
        if value.shape != (n,) or value.dtype != bool:
            raise ValueError(
                f"{name}: expected a ({n},) boolean mask, got {value.dtype} {value.shape}"
            )
        masks.append(value)
    attach, onto = masks
    if not attach.any():
        raise ValueError("attach: selects no vertex")
    if not onto.any():
        raise ValueError("onto: selects no vertex")
    if (attach & onto).any():
        raise ValueError(f"onto: shares {(attach & onto).sum()} vertices with attach")
    coo = graph.tocoo()
    keep = ~(attach[coo.col] & ~attach[coo.row])  # no edge into attach from outside
    targets = np.flatnonzero(onto)
    sources = np.flatnonzero(attach)
    length, nearest = KDTree(vertices[targets]).query(vertices[sources])
    rows = np.concatenate([coo.row[keep], sources])
    cols = np.concatenate([coo.col[keep], targets[nearest]])
    data = np.concatenate([coo.data[keep], np.maximum(length, MIN_EDGE_LENGTH)])
    # an exit may repeat a kept edge (onto a neighbour): keep the shorter, not their sum
    return _min_duplicates(rows, cols, data, n)


def _min_duplicates(rows, cols, data, n) -> sp.csr_matrix:
    """A csr matrix keeping the smallest weight of repeated (row, col) entries."""
    key = rows.astype(np.int64) * n + cols
    order = np.lexsort((data, key))
    key, first = np.unique(key[order], return_index=True)
    return sp.csr_matrix((data[order][first], (key // n, key % n)), shape=(n, n))


def _check_graph(graph: Any) -> sp.csr_matrix:
    if not sp.issparse(graph) or graph.ndim != 2 or graph.shape[0] != graph.shape[1]:
        raise TypeError(
            f"graph: expected a square scipy.sparse matrix (edge_graph), got {type(graph).__name__}"
        )
    return graph


def weighted_geodesic_distance(
    graph: sp.csr_matrix, sources: Int[ArrayLike, " H"], *, limit: float = np.inf
) -> Float32[np.ndarray, "H V"]:
    """(H, V) float32 shortest-path distance from each source vertex to every vertex, along
    ``graph`` (``edge_graph``, or a directed one such as ``bridged_edge_graph``).

    Vertices farther than ``limit`` (or unreachable) get ``inf``; a finite limit makes many
    sources on a large mesh cheap.
    """
    graph = _check_graph(graph)
    sources = np.asarray(sources)
    n = sparse_shape(graph)[0]
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
    # directed: a symmetric graph (edge_graph) gives the undirected distances
    return dijkstra(graph, directed=True, indices=sources, limit=limit).astype(np.float32)


def farthest_point_vertices(
    vertices: Float[ArrayLike, "V 3"],
    n: int,
    start: int = 0,
    *,
    graph: sp.csr_matrix | None = None,
) -> Int[np.ndarray, " n"]:
    """(n,) vertex indices by farthest-point sampling from vertex ``start``: evenly spread
    points (e.g. handles, as an animator would place them).

    Distances are Euclidean, or with ``graph`` (``edge_graph``, (V, V)) geodesic along the
    mesh: then both lips and both eyelids get their share although they touch in 3D. Another
    connected component is infinitely far, so each component gets a point first.
    """
    vertices = check_vertices(vertices)
    if isinstance(n, bool) or not isinstance(n, int | np.integer):
        raise TypeError(f"n: expected an integer count, got {n!r}")
    if not 1 <= n <= len(vertices):
        raise ValueError(f"n: expected 1 <= n <= {len(vertices)}, got {n}")
    if isinstance(start, bool) or not isinstance(start, int | np.integer):
        raise TypeError(f"start: expected an integer vertex index, got {start!r}")
    if not 0 <= start < len(vertices):
        raise ValueError(f"start: expected a vertex index in [0, {len(vertices)}), got {start}")
    if graph is not None:
        graph = _check_graph(graph)
        if sparse_shape(graph) != (len(vertices), len(vertices)):
            raise ValueError(
                f"graph: expected shape ({len(vertices)}, {len(vertices)}), got {graph.shape}"
            )

    def distance(i):
        if graph is None:
            return np.linalg.norm(vertices - vertices[i], axis=1)
        return weighted_geodesic_distance(graph, np.array([i]))[0]

    chosen = [int(start)]
    nearest = distance(start)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(nearest)))
        nearest = np.minimum(nearest, distance(chosen[-1]))
    return np.asarray(chosen, np.int32)
