"""Another triangulation of the same surface, with a map that carries per-vertex data.

Three remeshings of a real head, each returning a ``Remeshed`` (new vertices, faces and a
``SurfaceMap`` from the new vertices to points on the original surface):

* ``decimate``: quadric edge-collapse decimation (``fast_simplification``) of each connected
  component separately, so eyes, teeth and gums stay separate parts; the new vertices are
  snapped to their closest point on the same component of the original surface.
* ``subdivide``: midpoint (1-to-4) subdivision; the surface is unchanged and the map exact.
* ``flip_quad_split``: ICT's quads are stored fan-split as (a, b, c), (a, c, d); this splits
  each along the other diagonal, (a, b, d), (b, c, d). Same vertices, other triangles.

A ``SurfaceMap`` stores, for each new vertex, a triangle of the original mesh and barycentric
coordinates of its closest point there; ``carry`` interpolates any per-vertex data
(positions, blendshape deltas) linearly over that triangle, so a remeshed head keeps a
ground-truth rig (``canrig_jax.rig.remesh_rig``). By construction
``map.carry(original_vertices)`` equals the new vertices.
"""

import collections
import dataclasses
import hashlib

import numpy as np
import scipy.sparse as sp
from jaxtyping import ArrayLike, Float, Int
from scipy.spatial import KDTree

from ._operators import check_mesh
from ._topology import connected_components


@dataclasses.dataclass(frozen=True)
class SurfaceMap:
    """Points on a source mesh: one triangle and barycentric coordinates per point.

    Attributes:
        triangle: (N,) index into ``source_faces``.
        barycentric: (N, 3) weights of that triangle's corners (non-negative, sum 1).
        source_faces: (F, 3) the source triangles; n_source: source vertex count.
        distance: (N,) distance from each query point to its surface point (0 when exact).
    """

    triangle: Int[np.ndarray, " N"]
    barycentric: Float[np.ndarray, "N 3"]
    source_faces: Int[np.ndarray, "F 3"]
    n_source: int
    distance: Float[np.ndarray, " N"]

    @property
    def n_points(self) -> int:
        return int(self.triangle.shape[0])

    def matrix(self) -> sp.csr_matrix:
        """(N, n_source) sparse interpolation matrix, three entries per row."""
        rows = np.repeat(np.arange(self.n_points), 3)
        cols = self.source_faces[self.triangle].ravel()
        return sp.csr_matrix(
            (self.barycentric.ravel(), (rows, cols)), shape=(self.n_points, self.n_source)
        )

    def carry(self, values: Float[ArrayLike, "..."]) -> Float[np.ndarray, "..."]:
        """Interpolate per-vertex data (..., n_source, C) or (..., n_source) to the points."""
        values = np.asarray(values)
        axis = values.ndim - 2 if values.ndim >= 2 else 0
        if values.ndim >= 2 and values.shape[-2] == self.n_source:
            corners = np.take(values, self.source_faces[self.triangle], axis=axis)  # (.., N, 3, C)
            return np.einsum("...nkc,nk->...nc", corners, self.barycentric)
        if values.shape[-1] == self.n_source:
            corners = np.take(values, self.source_faces[self.triangle], axis=-1)  # (..., N, 3)
            return np.einsum("...nk,nk->...n", corners, self.barycentric)
        raise ValueError(
            f"values: expected (..., {self.n_source}, C) or (..., {self.n_source}) per-vertex "
            f"data of the source mesh, got shape {values.shape}"
        )


@dataclasses.dataclass(frozen=True)
class Remeshed:
    """A new triangulation of a surface and the map from its vertices to the original.

    Attributes:
        vertices: (N, 3) new positions (on the original surface); faces: (F', 3).
        map: ``SurfaceMap`` of the new vertices on the original mesh.
        method: "decimate", "subdivide" or "flip_quad_split".
    """

    vertices: Float[np.ndarray, "N 3"]
    faces: Int[np.ndarray, "F 3"]
    map: SurfaceMap
    method: str

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def nearest_vertices(self, source_points: Float[ArrayLike, "L 3"]) -> Int[np.ndarray, " L"]:
        """(L,) index of the new vertex nearest each source point (e.g. landmark positions)."""
        return np.asarray(KDTree(self.vertices).query(np.asarray(source_points, np.float64))[1])


# --------------------------------------------------------------------------------------------
# Closest points on a triangle mesh
# --------------------------------------------------------------------------------------------


def _closest_on_triangles(p, a, b, c):
    """Closest points of p on triangles (a, b, c), all (N, 3): barycentrics (N, 3)
    (Ericson, Real-Time Collision Detection, 5.1.5), vectorised; degenerate triangles are
    handled by the vertex and edge regions."""
    split = lambda x: tuple(x[..., k] for k in range(3))  # noqa: E731
    return np.stack(_closest_barycentric(split(p), split(a), split(b), split(c)), axis=-1)


def _closest_barycentric(p, a, b, c):
    """``_closest_on_triangles`` with each point a tuple of its x, y, z arrays (any shape,
    broadcast): the barycentric weights of a, b and c, three arrays. Coordinate by
    coordinate, so no small (..., 3) axis is reduced; sums of three products in the order
    of ``(x * y).sum(-1)``."""

    def minus(u, v):
        return (u[0] - v[0], u[1] - v[1], u[2] - v[2])

    def dot(u, v):
        return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

    ab, ac, ap, bp, cp = minus(b, a), minus(c, a), minus(p, a), minus(p, b), minus(p, c)
    d1, d2, d3, d4, d5, d6 = (
        dot(ab, ap),
        dot(ac, ap),
        dot(ab, bp),
        dot(ac, bp),
        dot(ab, cp),
        dot(ac, cp),
    )
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    safe = lambda x: np.where(np.abs(x) > 1e-300, x, 1e-300)  # noqa: E731
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = safe(va + vb + vc)
        v, w = vb / denom, vc / denom
        w_bc = (d4 - d3) / safe((d4 - d3) + (d5 - d6))
        w_ac = d2 / safe(d2 - d6)
        v_ab = d1 / safe(d1 - d3)
    # the Voronoi region of each closest point, the first that holds (vertex regions first)
    regions = [
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc
    ]
    bary = [
        np.select(regions, [1.0, 0.0, 1 - v_ab, 0.0, 1 - w_ac, 0.0], 1 - v - w),
        np.select(regions, [0.0, 1.0, v_ab, 0.0, 0.0, 1 - w_bc], v),
        np.select(regions, [0.0, 0.0, 0.0, 1.0, w_ac, w_bc], w),
    ]
    bary = [np.clip(np.nan_to_num(x, nan=1.0 / 3.0), 0.0, 1.0) for x in bary]
    total = bary[0] + bary[1] + bary[2]
    return bary[0] / total, bary[1] / total, bary[2] / total


@dataclasses.dataclass(frozen=True)
class _SurfaceIndex:
    """What closest-point queries on one mesh share: KD-trees of its triangle centroids and
    vertices, each vertex's incident triangles (V, width), padded with -1, each triangle's
    radius about its centroid (F,) (its farthest corner) and the largest coordinate
    magnitude (the scale of rounding errors)."""

    centroids: KDTree
    vertices: KDTree
    ring: Int[np.ndarray, "V W"]
    radius: Float[np.ndarray, " F"]
    extent: float


_INDEXES: collections.OrderedDict[bytes, _SurfaceIndex] = collections.OrderedDict()
_INDEXES_KEPT = 8


def _build_index(vertices: np.ndarray, faces: np.ndarray) -> _SurfaceIndex:
    order = np.argsort(faces.ravel(), kind="stable")
    corner_vertex = faces.ravel()[order]
    degree = np.bincount(corner_vertex, minlength=vertices.shape[0])
    starts = np.concatenate([[0], np.cumsum(degree)[:-1]])
    slot = np.arange(order.size) - np.repeat(starts, degree)
    ring = np.full((vertices.shape[0], max(int(degree.max()), 1)), -1, np.int64)
    ring[corner_vertex, slot] = order // 3
    centroids = vertices[faces].mean(axis=1)
    radius = np.linalg.norm(vertices[faces] - centroids[:, None], axis=-1).max(axis=1)
    extent = float(np.abs(vertices).max(initial=0.0))
    return _SurfaceIndex(KDTree(centroids), KDTree(vertices), ring, radius, extent)


def _surface_index(vertices: np.ndarray, faces: np.ndarray) -> _SurfaceIndex:
    """The mesh's ``_SurfaceIndex``, built once per mesh content and kept for the last
    ``_INDEXES_KEPT`` meshes (an iterative fit queries the same surface many times)."""
    digest = hashlib.blake2b(vertices.tobytes(), digest_size=16)
    digest.update(faces.tobytes())
    key = digest.digest() + repr((vertices.shape, faces.shape)).encode()
    index = _INDEXES.pop(key, None) or _build_index(vertices, faces)
    _INDEXES[key] = index
    while len(_INDEXES) > _INDEXES_KEPT:
        _INDEXES.popitem(last=False)
    return index


def closest_surface_points(
    points: Float[ArrayLike, "N 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    n_candidates: int = 16,
) -> SurfaceMap:
    """Closest point of each query point on a triangle mesh, as a ``SurfaceMap``.

    Candidates are the ``n_candidates`` triangles with the nearest centroids plus every
    triangle at the nearest vertex; exact when the closest triangle is among them (always,
    in practice, for meshes of comparable or finer resolution than the query spacing). The
    mesh's search trees are kept for the next query on the same mesh.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    vertices, faces = check_mesh(vertices, faces)
    index = _surface_index(vertices, faces)
    n_candidates = min(n_candidates, faces.shape[0])
    centroid_distance, near = index.centroids.query(points, k=n_candidates)
    centroid_distance = centroid_distance.reshape(points.shape[0], -1)
    near = near.reshape(points.shape[0], -1)
    vertex_distance, nearest_vertex = index.vertices.query(points)
    ring = index.ring[nearest_vertex]  # the triangles at the nearest vertex
    # Which candidates to test: a triangle at the nearest vertex is no farther than that
    # vertex, so a centroid's triangle whose bounding sphere is farther is never the closest;
    # and a triangle at the nearest vertex already among the centroids' is tested there, once.
    # np.argmin over every candidate (centroids' first, then the ring) picks the first at the
    # least distance, and that one is always kept: the same triangle as testing them all.
    bound = np.where(ring[:, 0] >= 0, vertex_distance, np.inf)
    slack = 1e-9 * (index.extent + bound)  # rounding of both distances
    near_kept = centroid_distance - index.radius[near] <= (bound + slack)[:, None]
    tested = np.where(near_kept, near, -1)
    ring_kept = (ring >= 0) & ~(ring[:, :, None] == tested[:, None, :]).any(axis=-1)
    row, column = np.nonzero(np.concatenate([near_kept, ring_kept], axis=1))  # row by row
    candidate = np.concatenate([near, ring], axis=1)[row, column]
    # coordinate by coordinate: (M,) arrays of each corner's x, y and z
    corners = faces[candidate]  # (M, 3)
    coords = [np.ascontiguousarray(vertices[:, k]) for k in range(3)]
    tri = [tuple(coords[k][corners[:, j]] for k in range(3)) for j in range(3)]
    query = tuple(points[row, k] for k in range(3))
    bary = _closest_barycentric(query, *tri)
    gap = [_sum_of_products(bary, [t[k] for t in tri]) - query[k] for k in range(3)]
    distance = np.sqrt(gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2])
    # each point's first candidate at its least distance (rows are contiguous in ``row``)
    starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])
    least = np.flatnonzero(distance == np.minimum.reduceat(distance, starts)[row])
    best = least[np.r_[True, row[least][1:] != row[least][:-1]]]
    return SurfaceMap(
        triangle=candidate[best].astype(np.int64),
        barycentric=np.stack([x[best] for x in bary], axis=-1),
        source_faces=faces,
        n_source=int(vertices.shape[0]),
        distance=distance[best],
    )


def _sum_of_products(weights, values):
    """weights[0] * values[0] + weights[1] * values[1] + weights[2] * values[2], in that
    order (``np.einsum`` over a corner axis of three)."""
    return weights[0] * values[0] + weights[1] * values[1] + weights[2] * values[2]


def vertex_surface_map(
    faces: Int[ArrayLike, "F 3"], n_vertices: int, vertex_ids: Int[ArrayLike, " N"]
) -> SurfaceMap:
    """Exact map of ``vertex_ids`` of a mesh onto itself (a face at each vertex, one-hot)."""
    faces, vertex_ids = np.asarray(faces), np.asarray(vertex_ids)
    face_of = np.full(n_vertices, -1, np.int64)
    corner_of = np.zeros(n_vertices, np.int64)
    for j in range(3):
        face_of[faces[:, j]] = np.arange(faces.shape[0])
        corner_of[faces[:, j]] = j
    triangle = face_of[vertex_ids]
    barycentric = np.zeros((vertex_ids.size, 3))
    barycentric[np.arange(vertex_ids.size), corner_of[vertex_ids]] = 1.0
    return SurfaceMap(triangle, barycentric, faces, n_vertices, np.zeros(vertex_ids.size))


def _check_no_isolated(vertices: np.ndarray, faces: np.ndarray) -> None:
    used = np.zeros(vertices.shape[0], bool)
    used[faces.ravel()] = True
    if not used.all():
        bad = np.flatnonzero(~used)
        raise ValueError(
            f"vertices: {bad.size} isolated vertices (in no face), e.g. {bad[:5].tolist()}; "
            "a surface map needs every vertex on a triangle, remove them first"
        )


# --------------------------------------------------------------------------------------------
# Remeshings
# --------------------------------------------------------------------------------------------


def decimate(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    target_vertices: int,
    *,
    aggressiveness: float = 7.0,
    min_component_vertices: int = 8,
) -> Remeshed:
    """Quadric decimation to about ``target_vertices``, component by component.

    Each connected component keeps its share of the target (at least
    ``min_component_vertices``, or all its vertices when it is already that small); new
    vertices are snapped to the closest point on the same component of the original surface.

    Args:
        vertices, faces: the mesh (every vertex in some face).
        target_vertices: wanted vertex count (reached within a few per cent).
        aggressiveness: ``fast_simplification``'s ``agg`` (0 careful ... 10 fast).
        min_component_vertices: smallest vertex count a component is decimated to.
    """
    import fast_simplification

    vertices, faces = check_mesh(vertices, faces)
    _check_no_isolated(vertices, faces)
    n = vertices.shape[0]
    if isinstance(target_vertices, bool) or not isinstance(target_vertices, int | np.integer):
        raise TypeError(f"target_vertices: expected an integer count, got {target_vertices!r}")
    if not 4 <= int(target_vertices) <= n:
        raise ValueError(f"target_vertices: expected between 4 and {n}, got {target_vertices}")
    labels = connected_components(faces, n)
    face_label = labels[faces[:, 0]]
    ratio = target_vertices / n
    new_vertices, new_faces, triangles, barycentrics, distances = [], [], [], [], []
    offset = 0
    for label in np.unique(labels):
        component = np.flatnonzero(labels == label)
        face_ids = np.flatnonzero(face_label == label)
        local = np.full(n, -1, np.int64)
        local[component] = np.arange(component.size)
        sub_vertices, sub_faces = vertices[component], local[faces[face_ids]]
        goal = max(min_component_vertices, int(round(component.size * ratio)))
        if goal < component.size:
            out_v, out_f = fast_simplification.simplify(
                sub_vertices,
                sub_faces.astype(np.int32),
                target_reduction=1.0 - goal / component.size,
                agg=aggressiveness,
            )[:2]
            out_f = np.asarray(out_f, np.int64)
            out_f = out_f[
                (out_f[:, 0] != out_f[:, 1])
                & (out_f[:, 1] != out_f[:, 2])
                & (out_f[:, 2] != out_f[:, 0])
            ]
            used = np.unique(out_f)
            reindex = np.full(len(out_v), -1, np.int64)
            reindex[used] = np.arange(used.size)
            out_v, out_f = np.asarray(out_v, np.float64)[used], reindex[out_f]
        else:
            out_v, out_f = sub_vertices, sub_faces
        surface = closest_surface_points(out_v, sub_vertices, sub_faces)
        new_vertices.append(
            np.einsum("nk,nkd->nd", surface.barycentric, sub_vertices[sub_faces[surface.triangle]])
        )
        new_faces.append(out_f + offset)
        triangles.append(face_ids[surface.triangle])
        barycentrics.append(surface.barycentric)
        distances.append(surface.distance)
        offset += out_v.shape[0]
    surface_map = SurfaceMap(
        triangle=np.concatenate(triangles),
        barycentric=np.concatenate(barycentrics),
        source_faces=faces,
        n_source=n,
        distance=np.concatenate(distances),
    )
    return Remeshed(
        np.concatenate(new_vertices), np.concatenate(new_faces), surface_map, "decimate"
    )


def subdivide(vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]) -> Remeshed:
    """Midpoint subdivision: a vertex at every edge midpoint, each triangle split in four."""
    vertices, faces = check_mesh(vertices, faces)
    _check_no_isolated(vertices, faces)
    n = vertices.shape[0]
    corners = [(0, 1), (1, 2), (2, 0)]
    edges = np.concatenate([faces[:, [a, b]] for a, b in corners])
    edges = np.sort(edges, axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.reshape(3, faces.shape[0]).T + n  # (F, 3): midpoint of edge (0,1),(1,2),(2,0)
    m01, m12, m20 = inverse[:, 0], inverse[:, 1], inverse[:, 2]
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    new_faces = np.concatenate(
        [
            np.stack([a, m01, m20], 1),
            np.stack([m01, b, m12], 1),
            np.stack([m20, m12, c], 1),
            np.stack([m01, m12, m20], 1),
        ]
    )
    # Map: original vertices one-hot; each midpoint on a face holding its edge, (1/2, 1/2).
    base = vertex_surface_map(faces, n, np.arange(n))
    first_face = np.full(unique.shape[0], -1, np.int64)
    first_corner = np.zeros(unique.shape[0], np.int64)
    for j in range(3):
        first_face[inverse[:, j] - n] = np.arange(faces.shape[0])
        first_corner[inverse[:, j] - n] = j
    mid_bary = np.zeros((unique.shape[0], 3))
    rows = np.arange(unique.shape[0])
    mid_bary[rows, first_corner] = 0.5
    mid_bary[rows, (first_corner + 1) % 3] = 0.5
    surface_map = SurfaceMap(
        triangle=np.concatenate([base.triangle, first_face]),
        barycentric=np.concatenate([base.barycentric, mid_bary]),
        source_faces=faces,
        n_source=n,
        distance=np.zeros(n + unique.shape[0]),
    )
    new_vertices = np.concatenate([vertices, vertices[unique].mean(axis=1)])
    return Remeshed(new_vertices, new_faces, surface_map, "subdivide")


def quad_pairs(faces: Int[ArrayLike, "F 3"]) -> Int[np.ndarray, " Q"]:
    """(Q,) indices i where faces i, i+1 are one fan-split quad: (a, b, c), (a, c, d)."""
    faces = np.asarray(faces)
    candidate = (faces[:-1, 0] == faces[1:, 0]) & (faces[:-1, 2] == faces[1:, 1])
    pairs, i = [], 0
    flags = np.append(candidate, False)
    while i < faces.shape[0] - 1:
        if flags[i]:
            pairs.append(i)
            i += 2
        else:
            i += 1
    return np.asarray(pairs, np.int64)


def flip_quad_split(vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]) -> Remeshed:
    """Split every fan-split quad (a, b, c), (a, c, d) along the other diagonal:
    (a, b, d), (b, c, d). Vertices and the rest of the triangles are unchanged."""
    vertices, faces = check_mesh(vertices, faces)
    _check_no_isolated(vertices, faces)
    pairs = quad_pairs(faces)
    if pairs.size == 0:
        raise ValueError("faces: no fan-split quads (a, b, c), (a, c, d) to flip")
    new_faces = faces.copy()
    a, b, c = faces[pairs, 0], faces[pairs, 1], faces[pairs, 2]
    d = faces[pairs + 1, 2]
    new_faces[pairs] = np.stack([a, b, d], 1)
    new_faces[pairs + 1] = np.stack([b, c, d], 1)
    n = vertices.shape[0]
    return Remeshed(
        vertices.copy(), new_faces, vertex_surface_map(faces, n, np.arange(n)), "flip_quad_split"
    )
