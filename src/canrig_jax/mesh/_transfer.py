"""Deformation transfer (Sumner & Popović 2004): a source rig's expressions onto a new head.

For every source triangle s and expression k the deformation gradient
Q_ks = [v1 - v0, v2 - v0, n~]_k [v1 - v0, v2 - v0, n~]_0^{-1} (Sumner & Popović's frame with
the scaled normal n~ = n / sqrt|n|, the foundation's ``deformation_gradient`` code) is applied
to the edges of the corresponding target triangle t, and the target's positions are found by
one sparse least-squares solve, prefactorised once per target mesh:

    u_k = argmin_u  || D (x0 + u) - Q_{k s(t)} E0_t ||^2  +  lambda || u - a_k ||^2,

with D the (3T, V) edge-difference operator, E0 the target's rest edges, and a_k the source
deltas carried to the target vertices by the correspondence's surface map. Gradients and
anchors are first rotated into the target's orientation, Q -> R Q R^T and a -> s R a, with
(s, R) the similarity between the carried source neutral and the target, so the transfer
commutes with a rigid motion or scaling of the target. The small ridge
(``screening`` times the mean diagonal of D^T D) only fixes what edges cannot: the
translation of each connected component (jaw-driven lower teeth translate as a whole).

Anchored transfer (``static_below``): the ridge is weak, so the solve lets motion bleed into
regions the source leaves still (eyeballs, the back of the head move by a few hundredths of a
millimetre). With a threshold, per expression the target vertices whose anchor a_k is shorter
are held at exactly zero (Dirichlet constraints) and the system is solved on the others,
factorised per expression. Per-part anchoring (``static_parts``, labels of source parts):
a target vertex is held only when the whole source part its surface point lies on moves less
than the threshold, so a part is held as a whole or not at all (a target part whose closest
source points fall partly on a still region of a moving source part is not pinned there);
parts labelled -1 keep the per-vertex rule.

The correspondence is a ``TriangleCorrespondence``: a source triangle for every target
triangle plus a surface map of the target vertices on the source. On identical topology it is
the identity (``identity_correspondence``); otherwise ``closest_point_correspondence`` aligns
the source to the target by a similarity transform on landmarks (Umeyama), warps it with a
thin-plate spline through the same landmarks (a non-rigid alignment), matches connected
components (nearest by mean distance, preferring similar area; implausibly far matches are
refused) and takes closest points component by component; each target triangle is driven by
the source triangles under four points inside it (centroid and towards each corner), their
gradients averaged with source-area weights.
"""

import dataclasses

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jaxtyping import ArrayLike, Float, Float64, Int
from scipy.interpolate import RBFInterpolator
from scipy.spatial import KDTree

from .._checks import check_real
from ._deformation_gradient import triangle_frames
from ._operators import check_mesh
from ._remesh import SurfaceMap, closest_surface_points, vertex_surface_map
from ._topology import connected_components, vertex_adjacency

_EDGES = ((0, 1), (1, 2), (2, 0))


@dataclasses.dataclass(frozen=True)
class TriangleCorrespondence:
    """Which source triangle drives each target triangle, and where target vertices lie on
    the source.

    Attributes:
        source_triangle: (T,) source face per target face, or (T, S) S source faces
            sampled inside each target face (their gradients are averaged, weighted by
            source area).
        vertex_map: ``SurfaceMap`` of the target vertices on the source mesh.
        target_faces: (T, 3) the target triangles.
        method: "identity" or "closest_point".
        component_match: for "closest_point" with component matching, the source connected
            component matched to each target connected component (None otherwise).
    """

    source_triangle: Int[np.ndarray, " T *S"]
    vertex_map: SurfaceMap
    target_faces: Int[np.ndarray, "T 3"]
    method: str
    component_match: Int[np.ndarray, " C"] | None = None

    @property
    def n_target_vertices(self) -> int:
        return int(self.vertex_map.n_points)


def identity_correspondence(
    faces: Int[ArrayLike, "F 3"], n_vertices: int
) -> TriangleCorrespondence:
    """The correspondence of a mesh with itself (same topology, any shape)."""
    faces = np.asarray(faces, np.int64)
    return TriangleCorrespondence(
        np.arange(faces.shape[0]),
        vertex_surface_map(faces, n_vertices, np.arange(n_vertices)),
        faces,
        "identity",
    )


def similarity_transform(
    source_points: Float[ArrayLike, "L 3"], target_points: Float[ArrayLike, "L 3"]
) -> tuple[float, Float[np.ndarray, "3 3"], Float[np.ndarray, " 3"]]:
    """Least-squares scale s, rotation R and translation t with target ~ s R source + t
    (Umeyama 1991). Points are (L, 3), L >= 3."""
    x = np.asarray(source_points, np.float64)
    y = np.asarray(target_points, np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 3:
        raise ValueError(
            f"source_points, target_points: expected equal shapes (L, 3) with L >= 3, got "
            f"{x.shape} and {y.shape}"
        )
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    u, sigma, vt = np.linalg.svd(yc.T @ xc / x.shape[0])
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(sigma) @ sign) / np.mean(np.sum(xc**2, axis=1)))
    return scale, rotation, my - scale * rotation @ mx


_SAMPLES = np.array(
    [[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]]
)
"""Barycentric points sampled in each target face: the centroid and one towards each corner."""


def _component_areas(vertices, faces, labels) -> np.ndarray:
    cross = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    return np.bincount(labels[faces[:, 0]], 0.5 * np.linalg.norm(cross, axis=1), labels.max() + 1)


IMPLAUSIBLE_DISTANCE = 1.0
"""A component match is refused when the target component's vertices lie farther from the
matched source component, on average, than this fraction of the target component's size."""


def _match_components(source, source_faces, source_labels, target, target_faces, target_labels):
    """Source component for each target component: the nearest (smallest mean distance of the
    target component's vertices), unless a source component of similar area (ratio within
    1/2..2) is at most twice as far, which is then taken (area keeps teeth off the lips they
    sit behind; distance picks left or right). A match farther than ``IMPLAUSIBLE_DISTANCE``
    of the target component's size is refused (ValueError naming ``target_vertices``), but for
    a vertex no triangle uses (it takes the nearest part)."""
    source_area = _component_areas(source, source_faces, source_labels)
    target_area = _component_areas(target, target_faces, target_labels)
    trees = {c: KDTree(source[source_labels == c]) for c in np.unique(source_labels)}
    labels = np.array(sorted(trees))
    match = np.zeros(target_labels.max() + 1, np.int64)
    in_faces = np.bincount(target_labels[target_faces].ravel(), minlength=len(match)) > 0
    for label in np.unique(target_labels):
        points = target[target_labels == label]
        cost = np.array([trees[c].query(points)[0].mean() for c in labels])
        ratio = target_area[label] / np.maximum(source_area[labels], 1e-30)
        similar = (ratio > 0.5) & (ratio < 2.0) & (cost <= 2.0 * cost.min())
        chosen = np.flatnonzero(similar)[np.argmin(cost[similar])] if similar.any() else None
        chosen = int(np.argmin(cost)) if chosen is None else int(chosen)
        size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        if in_faces[label] and cost[chosen] > IMPLAUSIBLE_DISTANCE * max(size, 1e-12):
            raise ValueError(
                f"target_vertices: component {int(label)} ({points.shape[0]} vertices, size "
                f"{size:.3g}) is {cost[chosen]:.3g} from the nearest source part on average; "
                "no plausible match (is the head aligned, in the source's units and "
                "orientation, with correct landmarks?)"
            )
        match[label] = labels[chosen]
    return match


def _face_sides(sides: Int[np.ndarray, " V"], faces: Int[np.ndarray, "F 3"]) -> np.ndarray:
    """(F,) the side of each triangle: its corners' when all three share one, else -1."""
    corner = sides[faces]
    return np.where((corner == corner[:, :1]).all(axis=1), corner[:, 0], -1)


def _closest_on_side(points, point_side, vertices, faces, face_side) -> SurfaceMap:
    """``closest_surface_points``, except that a point of side s >= 0 never lands on a
    triangle of another side >= 0: such points are found again among the triangles of side s
    or -1 (``point_side`` None: no sides)."""
    found = closest_surface_points(points, vertices, faces)
    if point_side is None:
        return found
    landed = face_side[found.triangle]
    crossed = (point_side >= 0) & (landed >= 0) & (landed != point_side)
    if not crossed.any():
        return found
    triangle, barycentric = found.triangle.copy(), found.barycentric.copy()
    distance = found.distance.copy()
    for side in np.unique(point_side[crossed]):
        who = np.flatnonzero(crossed & (point_side == side))
        allowed = np.flatnonzero((face_side == side) | (face_side < 0))
        if allowed.size == 0:
            continue
        sub = closest_surface_points(points[who], vertices, faces[allowed])
        triangle[who] = allowed[sub.triangle]
        barycentric[who], distance[who] = sub.barycentric, sub.distance
    return dataclasses.replace(found, triangle=triangle, barycentric=barycentric, distance=distance)


def _smoothed_pull(
    source, source_faces, source_labels, target, target_faces, target_face_label, match,
    sides=None,
):  # fmt: skip
    """(V_s, 3) smooth displacement of the source towards its closest points on the target
    components matched to each source component (zero where none is matched); with
    ``sides`` = (source vertex sides, target face sides), never across a slit."""
    displacement = np.zeros_like(source)
    for component in np.unique(match):
        members = np.flatnonzero(source_labels == component)
        chosen = np.flatnonzero(np.isin(target_face_label, np.flatnonzero(match == component)))
        if chosen.size == 0:
            continue
        faces = target_faces[chosen]
        found = _closest_on_side(
            source[members],
            None if sides is None else sides[0][members],
            target,
            faces,
            None if sides is None else sides[1][chosen],
        )
        closest = np.einsum("nk,nkd->nd", found.barycentric, target[faces[found.triangle]])
        displacement[members] = closest - source[members]
    adjacency = vertex_adjacency(source_faces, len(source))
    degree = np.maximum(np.asarray(adjacency.sum(axis=1)).ravel(), 1.0)
    average = sp.diags(1.0 / degree) @ adjacency
    for _ in range(20):
        displacement = 0.5 * displacement + 0.5 * (average @ displacement)
    return displacement


def closest_point_correspondence(
    source_vertices: Float[ArrayLike, "Vs 3"],
    source_faces: Int[ArrayLike, "Fs 3"],
    target_vertices: Float[ArrayLike, "V 3"],
    target_faces: Int[ArrayLike, "F 3"],
    source_landmarks: Int[ArrayLike, " L"],
    target_landmarks: Int[ArrayLike, " L"],
    *,
    nonrigid: bool = True,
    match_components: bool = True,
    refine_iterations: int = 3,
    source_sides: Int[ArrayLike, " Vs"] | None = None,
    target_sides: Int[ArrayLike, " V"] | None = None,
) -> TriangleCorrespondence:
    """Correspondence of two heads of different topology from landmarks and closest points.

    Args:
        source_vertices, source_faces: the source head (the rig's neutral).
        target_vertices, target_faces: the target head.
        source_landmarks, target_landmarks: (L,) vertex indices of the same L >= 3 landmarks
            (e.g. ICT's Multi-PIE 68) on each mesh.
        nonrigid: after the similarity alignment, warp the source by a thin-plate spline that
            takes its landmarks onto the target's.
        match_components: restrict each target component to one source component, the
            nearest (preferring one of similar area when it is nearly as near: keeps teeth on
            teeth, eyes on eyes); the match is in ``component_match``, and a target component
            with no source part near it raises ValueError naming ``target_vertices``.
        refine_iterations: after the spline warp, times each source vertex is moved towards
            its closest point on the matched target components, the displacement smoothed
            over the source mesh (20 steps of neighbour averaging); a simple non-rigid ICP.
        source_sides, target_sides: (Vs,) and (V,) integer side of every vertex around the
            slits closest points must not cross (the lips of a closed mouth, the lids of an
            eye: e.g. 0 the upper lip, 1 the lower), -1 where any side may be reached. A
            point of side s >= 0 never lands on a triangle whose corners all lie on another
            side >= 0, in the alignment's refinement nor in the map (a triangle's side: its
            corners' when they share one, else -1). Both or neither.

    Returns:
        A ``TriangleCorrespondence`` for ``rig.deformation_transfer``: ``source_triangle``
        (T,), the source face that drives each target face, or (T, S), S source faces sampled
        inside each target face (their gradients are averaged, weighted by source area);
        ``vertex_map``, the ``SurfaceMap`` of the target vertices on the source mesh;
        ``target_faces`` (T, 3); ``method``, "closest_point"; ``component_match``, the source
        connected component matched to each target component (None without
        ``match_components``).
    """
    sv, sf = check_mesh(source_vertices, source_faces)
    tv, tf = check_mesh(target_vertices, target_faces)
    sl = np.asarray(source_landmarks, np.int64)
    tl = np.asarray(target_landmarks, np.int64)
    if sl.shape != tl.shape or sl.ndim != 1 or sl.size < 3:
        raise ValueError(
            f"source_landmarks, target_landmarks: expected equal (L,) vertex lists with L >= 3, "
            f"got {sl.shape} and {tl.shape}"
        )
    for name, ids, n in (("source_landmarks", sl, len(sv)), ("target_landmarks", tl, len(tv))):
        if ids.min() < 0 or ids.max() >= n:
            raise ValueError(f"{name}: vertex indices must lie in [0, {n})")
    sides = _check_sides(source_sides, target_sides, len(sv), len(tv))
    scale, rotation, shift = similarity_transform(sv[sl], tv[tl])
    aligned = scale * sv @ rotation.T + shift
    if nonrigid:
        warp = RBFInterpolator(aligned[sl], tv[tl] - aligned[sl], kernel="thin_plate_spline")
        aligned = aligned + warp(aligned)

    source_labels = connected_components(sf, len(sv))
    target_labels = connected_components(tf, len(tv))
    if not match_components:
        source_labels = np.zeros_like(source_labels)
        target_labels = np.zeros_like(target_labels)
    match = _match_components(aligned, sf, source_labels, tv, tf, target_labels)
    target_face_component = target_labels[tf[:, 0]]
    pull_sides = None if sides is None else (sides[0], _face_sides(sides[1], tf))
    for _ in range(refine_iterations if nonrigid else 0):
        aligned = aligned + _smoothed_pull(
            aligned, sf, source_labels, tv, tf, target_face_component, match, pull_sides,
        )  # fmt: skip
    triangle, barycentric, distance, source_triangle = _closest_by_component(
        tv, tf, target_labels, aligned, sf, source_labels, match, sides
    )
    vertex_map = SurfaceMap(triangle, barycentric, sf, len(sv), distance)
    return TriangleCorrespondence(
        source_triangle,
        vertex_map,
        tf,
        "closest_point",
        match if match_components else None,
    )


def _closest_by_component(tv, tf, target_labels, aligned, sf, source_labels, match, sides):
    """The vertex map and the sampled source triangles, each target component on its matched
    source component (and on its own side of every slit when ``sides`` is given): (triangle
    (V,), barycentric (V, 3), distance (V,), source_triangle (T, S))."""
    if sides is not None:
        face_side = (_face_sides(sides[0], sf), _face_sides(sides[1], tf))
    source_face_label = source_labels[sf[:, 0]]
    target_face_label = target_labels[tf[:, 0]]
    triangle = np.zeros(len(tv), np.int64)
    barycentric = np.zeros((len(tv), 3))
    distance = np.zeros(len(tv))
    source_triangle = np.zeros((len(tf), len(_SAMPLES)), np.int64)
    samples = np.einsum("sk,tkd->tsd", _SAMPLES, tv[tf])  # (T, S, 3) points in each face
    for label in np.unique(target_labels):
        members = np.flatnonzero(target_labels == label)
        chosen = np.flatnonzero(source_face_label == match[label])
        chosen_side = None if sides is None else face_side[0][chosen]
        sub = _closest_on_side(
            tv[members], None if sides is None else sides[1][members], aligned, sf[chosen],
            chosen_side,
        )  # fmt: skip
        triangle[members] = chosen[sub.triangle]
        barycentric[members] = sub.barycentric
        distance[members] = sub.distance
        faces_here = np.flatnonzero(target_face_label == label)
        if faces_here.size == 0:  # vertices no triangle uses
            continue
        points = samples[faces_here].reshape(-1, 3)
        point_side = None
        if sides is not None:
            point_side = np.repeat(face_side[1][faces_here], len(_SAMPLES))
        source_triangle[faces_here] = chosen[
            _closest_on_side(points, point_side, aligned, sf[chosen], chosen_side).triangle
        ].reshape(-1, len(_SAMPLES))
    return triangle, barycentric, distance, source_triangle


def _check_sides(source_sides, target_sides, n_source: int, n_target: int):
    """(source sides, target sides) as int64 arrays, or None when neither is given."""
    if source_sides is None and target_sides is None:
        return None
    if source_sides is None or target_sides is None:
        raise ValueError("source_sides, target_sides: give both or neither")
    out = []
    for name, sides, n in (("source_sides", source_sides, n_source),
                           ("target_sides", target_sides, n_target)):  # fmt: skip
        sides = np.asarray(sides)
        if sides.shape != (n,) or (sides.size and not np.issubdtype(sides.dtype, np.integer)):
            raise ValueError(
                f"{name}: expected ({n},) integer sides (-1: any), got {sides.shape} {sides.dtype}"
            )
        out.append(sides.astype(np.int64))
    return tuple(out)


def _difference_operator(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(3T, V): row (e, t) = x[faces[t, b]] - x[faces[t, a]] for edge e = (a, b), edge-major."""
    n_tri = faces.shape[0]
    rows = np.arange(3 * n_tri)
    heads = np.concatenate([faces[:, b] for _, b in _EDGES])
    tails = np.concatenate([faces[:, a] for a, _ in _EDGES])
    return sp.csr_matrix(
        (np.r_[np.ones(3 * n_tri), -np.ones(3 * n_tri)], (np.r_[rows, rows], np.r_[heads, tails])),
        shape=(3 * n_tri, n_vertices),
    )


def transfer_deltas(
    source_neutral: Float[ArrayLike, "Vs 3"],
    source_deltas: Float[ArrayLike, "K Vs 3"],
    source_faces: Int[ArrayLike, "Fs 3"],
    target_neutral: Float[ArrayLike, "V 3"],
    correspondence: TriangleCorrespondence,
    *,
    screening: float = 1e-3,
    min_area: float = 1e-10,
    batch_size: int = 8,
    static_below: float | None = None,
    static_parts: Int[ArrayLike, " Vs"] | None = None,
) -> Float64[np.ndarray, "K V 3"]:
    """Transfer every blendshape (``source_deltas``) of a source mesh onto ``target_neutral``.

    Args:
        source_neutral: (Vs, 3) source rest vertices, triangulated by ``source_faces``.
        source_deltas: (K, Vs, 3) source blendshape offsets.
        source_faces: (Fs, 3) source triangles.
        target_neutral: (V, 3) target rest vertices, triangulated by
            ``correspondence.target_faces``.
        correspondence: from ``identity_correspondence`` or ``closest_point_correspondence``.
        screening: ridge towards the carried source deltas, relative to the mean diagonal of
            D^T D (fixes each component's translation; small keeps shape from gradients).
        min_area: source triangles below this area (squared units) in the neutral or an
            expression keep the identity deformation.
        batch_size: expressions per solve batch.
        static_below: anchored transfer: per expression, the target vertices whose carried
            source delta (the anchor a_k, in the target's orientation and size) is shorter than
            this (target units) are held at zero displacement (Dirichlet constraints; the
            system is reduced to the other vertices and factorised per expression), so motion
            does not bleed into what the source leaves still. None (default): plain transfer.
        static_parts: per-part anchoring (needs ``static_below``): (Vs,) integer part label
            of every source vertex (e.g. its connected component), -1 for vertices anchored
            per vertex. A target vertex whose surface point lies on a part >= 0 (the label of
            the point's nearest triangle corner, largest barycentric weight) is held at zero
            in an expression only when every vertex of that source part moves less than
            ``static_below`` there (scaled like the anchors); on a part -1 the per-vertex rule
            applies. None (default): per vertex everywhere.

    Returns:
        (K, V, 3) float64 target blendshape offsets. ``canrig_jax.rig.deformation_transfer``
        wraps this for a ``BlendshapeRig``.
    """
    source_neutral, source_faces_all, source_deltas, tv, target_faces = _check_transfer(
        source_neutral, source_deltas, source_faces, target_neutral, correspondence,
        screening, static_below,
    )  # fmt: skip
    part_of_target, part_members = _static_parts(
        static_parts, static_below, correspondence.vertex_map, source_neutral.shape[0]
    )
    samples = _source_samples(
        source_neutral, source_faces_all, correspondence.source_triangle, min_area
    )
    target_edges = np.stack(
        [tv[target_faces[:, b]] - tv[target_faces[:, a]] for a, b in _EDGES], axis=-1
    )  # (T, 3 coords, 3 edges)

    n_vertices = tv.shape[0]
    difference, system, solve, ridge = _screened_system(target_faces, n_vertices, screening)
    rest_difference = difference @ tv  # (3T, 3)
    # Source gradients and anchor deltas are expressed in the target's orientation (and the
    # anchors in its size): the similarity taking the source neutral, carried to the target
    # vertices, onto the target neutral. Without it a rotated target would be deformed along
    # the source's axes (Sumner & Popović assume aligned meshes).
    scale, rotation, _ = similarity_transform(correspondence.vertex_map.carry(source_neutral), tv)
    anchor_map = scale * rotation

    deltas = np.zeros((source_deltas.shape[0], n_vertices, 3))
    for start in range(0, source_deltas.shape[0], batch_size):
        chunk = source_deltas[start : start + batch_size]
        gradient = _source_gradients(source_neutral[None] + chunk, samples, min_area)
        gradient = rotation @ gradient @ rotation.T  # in the target's orientation
        edges = gradient @ target_edges  # (B, T, 3 coords, 3 edges)
        wanted = np.moveaxis(edges, -1, 1).reshape(chunk.shape[0], -1, 3)  # (B, 3T, 3)
        anchor = correspondence.vertex_map.carry(chunk) @ anchor_map.T  # (B, V, 3)
        rhs = difference.T @ np.moveaxis(wanted - rest_difference, 0, 1).reshape(
            wanted.shape[1], -1
        ) + ridge * np.moveaxis(anchor, 0, 1).reshape(n_vertices, -1)
        if static_below is None:
            deltas[start : start + chunk.shape[0]] = np.moveaxis(
                solve(rhs).reshape(n_vertices, chunk.shape[0], 3), 1, 0
            )
            continue
        rhs = rhs.reshape(n_vertices, chunk.shape[0], 3)
        free = _free_vertices(
            anchor, chunk, scale, static_below, part_of_target, part_members
        )  # (B, V)
        for b in range(chunk.shape[0]):
            deltas[start + b] = _anchored_solve(system, solve, rhs[:, b], free[b])
    return deltas


def _check_transfer(
    source_neutral, source_deltas, source_faces, target_neutral, correspondence, screening,
    static_below,
):  # fmt: skip
    """``transfer_deltas``'s checked arrays: (source neutral, source faces, source deltas
    float64, target neutral float64, target faces)."""
    source_neutral, source_faces_all = check_mesh(source_neutral, source_faces)
    source_deltas = np.asarray(source_deltas)
    if source_deltas.ndim != 3 or source_deltas.shape[1:] != source_neutral.shape:
        raise ValueError(
            f"source_deltas: expected shape (K, {source_neutral.shape[0]}, 3), got "
            f"{source_deltas.shape}"
        )
    source_deltas = source_deltas.astype(np.float64)
    if not np.all(np.isfinite(source_deltas)):
        raise ValueError("source_deltas: contains non-finite values")
    tv = np.asarray(target_neutral)
    if tv.ndim != 2 or tv.shape[1] != 3:
        raise ValueError(f"target_neutral: expected shape (V, 3), got {tv.shape}")
    check_real("target_neutral", tv)
    tv = tv.astype(np.float64)
    if not np.all(np.isfinite(tv)):
        raise ValueError("target_neutral: contains non-finite positions")
    if correspondence.n_target_vertices != tv.shape[0]:
        raise ValueError(
            f"target_neutral: {tv.shape[0]} vertices, the correspondence maps "
            f"{correspondence.n_target_vertices}"
        )
    tv, target_faces = check_mesh(tv, np.asarray(correspondence.target_faces, np.int64))
    if correspondence.vertex_map.n_source != source_neutral.shape[0]:
        raise ValueError(
            f"correspondence: maps onto a source of {correspondence.vertex_map.n_source} "
            f"vertices, the source mesh has {source_neutral.shape[0]}"
        )
    if not (np.isfinite(screening) and screening > 0):
        raise ValueError(f"screening: expected a positive ridge, got {screening}")
    if static_below is not None and not (
        isinstance(static_below, (int, float, np.floating, np.integer))
        and np.isfinite(static_below)
        and static_below >= 0
    ):
        raise ValueError(
            f"static_below: expected None or a finite length >= 0, got {static_below!r}"
        )
    return source_neutral, source_faces_all, source_deltas, tv, target_faces


@dataclasses.dataclass(frozen=True)
class _SourceSamples:
    """The source triangles sampled for each target triangle, each distinct one once (target
    triangles share source triangles: the gradients are computed once per source triangle
    and gathered per sample).

    Attributes:
        faces: (U, 3) the distinct source triangles; of_sample: (T * S,) which of them each
            sample is; weight: (T, S) area weights summing to 1 (0 for degenerate ones);
        rest_ok: (U,) which are not degenerate; inverse_rest: (U, 3, 3) inverse rest frames.
    """

    faces: np.ndarray
    of_sample: np.ndarray
    weight: np.ndarray
    rest_ok: np.ndarray
    inverse_rest: np.ndarray


def _source_samples(source_neutral, source_faces_all, source_triangle, min_area):
    """The ``_SourceSamples`` of ``source_triangle`` (T,) or (T, S)."""
    source_triangle = np.asarray(source_triangle, np.int64)
    source_triangle = source_triangle.reshape(source_triangle.shape[0], -1)  # (T, S)
    n_samples = source_triangle.shape[1]
    distinct, of_sample = np.unique(source_triangle.ravel(), return_inverse=True)
    source_faces = source_faces_all[distinct]

    rest_frame, rest_area = triangle_frames(source_neutral, source_faces)
    rest_ok = rest_area >= min_area
    sample_weight = np.where(rest_ok, rest_area, 0.0)[of_sample].reshape(-1, n_samples)
    sample_weight /= np.maximum(sample_weight.sum(axis=1, keepdims=True), 1e-300)
    inverse_rest = np.linalg.inv(np.where(rest_ok[:, None, None], rest_frame, np.eye(3)))
    return _SourceSamples(source_faces, of_sample, sample_weight, rest_ok, inverse_rest)


def _screened_system(target_faces, n_vertices: int, screening: float):
    """(edge-difference operator D (3T, V), D^T D + ridge I, its factorised solve, ridge)."""
    difference = _difference_operator(target_faces, n_vertices)
    normal_matrix = (difference.T @ difference).tocsc()
    ridge = screening * normal_matrix.diagonal().mean()
    system = (normal_matrix + ridge * sp.identity(n_vertices)).tocsc()
    solve = spla.factorized(system)
    return difference, system, solve, ridge


def _source_gradients(posed, samples: _SourceSamples, min_area):
    """(B, T, 3, 3) deformation gradient of each target triangle: the area-weighted mean
    over its sampled source triangles of ``posed`` (B, Vs, 3) (identity where degenerate)."""
    sample_weight = samples.weight
    n_samples = sample_weight.shape[1]
    frame, area = triangle_frames(posed, samples.faces)
    gradient = frame @ samples.inverse_rest  # (B, U, 3, 3)
    keep = samples.rest_ok[None] & (area >= min_area)
    gradient = np.where(keep[..., None, None], gradient, np.eye(3))[:, samples.of_sample]
    gradient = gradient.reshape(posed.shape[0], -1, n_samples, 3, 3)
    gradient = np.einsum("btsij,ts->btij", gradient, sample_weight)
    no_weight = sample_weight.sum(axis=1) == 0
    gradient[:, no_weight] = np.eye(3)
    return gradient


def _free_vertices(anchor, chunk, scale, static_below, part_of_target, part_members):
    """(B, V) the target vertices anchored transfer solves for in each expression (the
    others are held at zero): by the carried anchor, or by their source part's motion."""
    free = np.linalg.norm(anchor, axis=-1) >= static_below  # (B, V) per vertex
    if part_of_target is not None:
        motion = scale * np.linalg.norm(chunk, axis=-1)  # (B, Vs), target units
        moving_part = np.stack(
            [motion[:, members].max(axis=1) >= static_below for members in part_members], 1
        )  # (B, parts)
        by_part = part_of_target >= 0
        free[:, by_part] = moving_part[:, part_of_target[by_part]]
    return free


def _static_parts(static_parts, static_below, vertex_map: SurfaceMap, n_source: int):
    """Checked ``static_parts``: ((V,) index of each target vertex's source part, -1 for the
    per-vertex rule; list of each part's source vertices), or (None, None) when not given."""
    if static_parts is None:
        return None, None
    labels = np.asarray(static_parts)
    if labels.shape != (n_source,) or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(
            f"static_parts: expected ({n_source},) integer part labels of the source vertices, "
            f"got {labels.dtype} {labels.shape}"
        )
    if labels.min() < -1:
        raise ValueError("static_parts: labels must be >= 0, or -1 for per-vertex anchoring")
    if static_below is None:
        raise ValueError("static_parts: per-part anchoring needs static_below (a threshold)")
    parts, index = np.unique(labels, return_inverse=True)
    corners = vertex_map.source_faces[vertex_map.triangle]  # (V, 3)
    nearest = corners[np.arange(corners.shape[0]), np.argmax(vertex_map.barycentric, axis=1)]
    part_of_target = np.where(labels[nearest] >= 0, index[nearest], -1)
    members = [np.flatnonzero(index == i) for i in range(parts.size)]
    return part_of_target, members


def _anchored_solve(system, solve, rhs: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(V, 3) solution of ``system`` u = ``rhs`` with u = 0 on the vertices not ``free``
    (Dirichlet: the rows and columns of the fixed vertices are dropped; their value is zero, so
    the right-hand side needs no correction)."""
    out = np.zeros_like(rhs)
    if free.all():
        return solve(rhs)
    if not free.any():
        return out
    index = np.flatnonzero(free)
    out[index] = spla.splu(system[index][:, index].tocsc()).solve(rhs[index])
    return out
