"""Sparse targets: the rig seen at a few points of its surface (mocap markers, tracked
landmarks), for ``prepare(rig, points=...)``.

A point is a vertex or a barycentric combination of a triangle's corners, so at the points the
rig is again a blendshape rig, exactly: its neutral, deltas and correctives are the same
barycentric combinations of the full rig's (every term of ``evaluate`` is linear in the
vertex data). The inverse-rig methods then solve from the points' positions alone.
"""

from typing import Any

import numpy as np
from jaxtyping import Float, Int

from ..mesh import SurfaceMap
from ..rig import BlendshapeRig, Corrective

BARYCENTRIC_TOL = 1e-4
"""How far barycentric coordinates may be from non-negative and summing to 1."""


def _corners(
    rig: BlendshapeRig, points: Any
) -> tuple[Int[np.ndarray, "N 3"], Float[np.ndarray, "N 3"]]:
    """(N, 3) vertex indices and (N, 3) weights of each point (a vertex: weight 1 on it)."""
    v = rig.n_vertices
    if isinstance(points, SurfaceMap):
        if points.n_source != v:
            raise ValueError(
                f"points: the SurfaceMap binds points to a mesh of {points.n_source} vertices, "
                f"the rig has {v}"
            )
        faces, triangle, weights = points.source_faces, points.triangle, points.barycentric
    elif isinstance(points, tuple) and len(points) == 2:
        if rig.faces is None:
            raise ValueError("points: (triangles, barycentric) needs a rig with faces")
        faces = np.asarray(rig.faces)
        triangle, weights = (np.asarray(p) for p in points)
    else:
        vertices = np.asarray(points)
        if (
            vertices.ndim != 1
            or vertices.size == 0
            or not np.issubdtype(vertices.dtype, np.integer)
        ):
            raise ValueError(
                "points: expected (N,) vertex indices, (triangles (N,), barycentric (N, 3)) on "
                f"the rig's faces, or a mesh.SurfaceMap; got an array of shape {vertices.shape} "
                f"and dtype {vertices.dtype}"
            )
        outside = vertices[(vertices < 0) | (vertices >= v)]
        if outside.size:
            raise ValueError(
                f"points: vertex indices {outside[:10].tolist()} are outside the rig's {v} vertices"
            )
        corners = np.repeat(vertices[:, None], 3, axis=1).astype(np.int64)
        return corners, np.tile([1.0, 0.0, 0.0], (vertices.size, 1))
    faces, triangle = np.asarray(faces), np.asarray(triangle)
    weights = np.asarray(weights, np.float64)
    n = triangle.shape[0] if triangle.ndim == 1 else -1
    if n <= 0 or weights.shape != (n, 3) or not np.issubdtype(triangle.dtype, np.integer):
        raise ValueError(
            f"points: expected (N,) triangle indices and (N, 3) barycentric coordinates, got "
            f"shapes {triangle.shape} and {weights.shape}"
        )
    outside = triangle[(triangle < 0) | (triangle >= faces.shape[0])]
    if outside.size:
        raise ValueError(
            f"points: triangles {outside[:10].tolist()} are outside the mesh's {faces.shape[0]}"
        )
    bad = ~np.isfinite(weights).all(1)
    bad |= (weights.min(1) < -BARYCENTRIC_TOL) | (np.abs(weights.sum(1) - 1) > BARYCENTRIC_TOL)
    if bad.any():
        raise ValueError(
            f"points: points {np.flatnonzero(bad)[:10].tolist()} are outside their triangle "
            "(barycentric coordinates must be >= 0 and sum to 1)"
        )
    return faces[triangle].astype(np.int64), weights


def points_rig(rig: BlendshapeRig, points: Any) -> BlendshapeRig:
    """The rig at ``points`` (see the module docstring): (N,) vertex indices, (triangles (N,),
    barycentric (N, 3)) on ``rig.faces``, or a ``mesh.SurfaceMap`` onto the rig's mesh (e.g.
    ``mesh.bind_points``). Its mesh is the N points (no faces); names and units are the rig's.
    Raises a ValueError naming ``points`` for points outside the mesh."""
    corners, weights = _corners(rig, points)

    def at_points(data: np.ndarray) -> Float[np.ndarray, "*C N 3"]:  # (..., V, 3) -> (..., N, 3)
        return np.einsum("...njd,nj->...nd", data[..., corners, :], weights)

    neutral = at_points(np.asarray(rig.neutral, np.float64))
    deltas = at_points(np.asarray(rig.deltas, np.float64))
    correctives = []
    for table in rig.correctives:
        support = np.asarray(table.vertices)
        slot = np.full(rig.n_vertices + 1, support.size, np.int64)  # support.size: not moved
        slot[support] = np.arange(support.size)
        padded = np.concatenate(
            [np.asarray(table.deltas, np.float64), np.zeros((table.indices.shape[0], 1, 3))], 1
        )
        moved = np.einsum("cnjd,nj->cnd", padded[:, slot[corners]], weights)
        keep = np.flatnonzero((slot[corners] < support.size).any(axis=1)).astype(np.int32)
        correctives.append(Corrective(table.indices, keep, moved[:, keep].astype(np.float32)))
    return BlendshapeRig(
        neutral.astype(np.float32),
        deltas.astype(np.float32),
        tuple(correctives),
        rig.names,
        None,
        units=rig.units,
    )
