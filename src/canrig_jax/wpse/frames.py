"""Per-vertex local frames of a posed mesh, so pose-space edits turn with the face.

An edit sculpted with the jaw open is a displacement in world space at that pose; stored in
the local frame (tangent, bitangent, normal) of the posed base mesh, it is rotated back into
world space with the frame of the mesh at run time, so it follows the jaw (Seol et al. store
edits in the local coordinates of the deformed base mesh the same way).

The normal of vertex v is the area-weighted sum of its incident triangle normals; the tangent
is the edge to one fixed neighbour of v, projected onto the tangent plane; the bitangent
completes a right-handed orthonormal frame. Topology (incident faces, the neighbour) is
computed once per mesh and vertex set, in NumPy; the frames themselves are a jit-able
function of the posed vertices, evaluated only at the edited vertices.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int


class LocalFrames(eqx.Module):
    """Topology needed to build frames at ``vertices`` of a mesh.

    Attributes:
        vertices: (S,) vertices that get a frame.
        faces: (S, D, 3) incident triangles of each vertex, padded by repeating one.
        weight: (S, D) 1 for a real incident triangle, 0 for padding.
        neighbour: (S,) the neighbour whose edge gives the tangent.
    """

    vertices: Int[Array, " S"]
    faces: Int[Array, "S D 3"]
    weight: Float[Array, "S D"]
    neighbour: Int[Array, " S"]

    @property
    def n_frames(self) -> int:
        return int(self.vertices.shape[0])


def local_frames(
    faces: Int[ArrayLike, "F 3"], vertices: Int[ArrayLike, " S"], n_vertices: int
) -> LocalFrames:
    """Incident triangles and tangent neighbour of every vertex in ``vertices``.

    Raises ValueError for face or vertex indices out of range, or a vertex on no triangle.
    """
    faces = np.asarray(faces, np.int64)
    vertices = np.asarray(vertices, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise ValueError(f"faces: vertex indices must lie in [0, {n_vertices})")
    if vertices.ndim != 1:
        raise ValueError(f"vertices: expected shape (S,), got {vertices.shape}")
    if vertices.size and (vertices.min() < 0 or vertices.max() >= n_vertices):
        raise ValueError(f"vertices: indices must lie in [0, {n_vertices})")
    corner_vertex = faces.reshape(-1)
    order = np.argsort(corner_vertex, kind="stable")
    counts = np.bincount(corner_vertex, minlength=n_vertices)
    starts = np.concatenate([[0], np.cumsum(counts)])
    degree = counts[vertices]
    if vertices.size and degree.min() == 0:
        lonely = vertices[degree == 0][:5].tolist()
        raise ValueError(f"vertices: {lonely} lie on no triangle, so they have no frame")
    width = int(degree.max(initial=1))
    slot = np.minimum(np.arange(width)[None, :], degree[:, None] - 1)
    corner = order[starts[vertices][:, None] + slot]  # (S, D) flat corner indices
    face_index = corner // 3
    # Rotate each incident triangle so that the vertex comes first: (v, a, b) keeps the
    # triangle's orientation and makes cross(a - v, b - v) its normal.
    position = corner % 3
    rolled = np.stack([faces[face_index, (position + j) % 3] for j in range(3)], axis=-1)
    neighbour = rolled[:, 0, 1]
    weight = (np.arange(width)[None, :] < degree[:, None]).astype(np.float32)
    return LocalFrames(
        jnp.asarray(vertices, jnp.int32),
        jnp.asarray(rolled, jnp.int32),
        jnp.asarray(weight),
        jnp.asarray(neighbour, jnp.int32),
    )


def frame_matrices(frames: LocalFrames, posed: Float[Array, "V 3"]) -> Float[Array, "S 3 3"]:
    """(S, 3, 3) orthonormal frames; columns are tangent, bitangent, normal in world space."""
    corners = posed[frames.faces]  # (S, D, 3 corners, 3)
    normal = jnp.einsum(
        "sd,sdc->sc",
        frames.weight,
        jnp.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0]),
    )
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    edge = posed[frames.neighbour] - posed[frames.vertices]
    tangent = edge - jnp.sum(edge * normal, axis=-1, keepdims=True) * normal
    tangent = tangent / jnp.linalg.norm(tangent, axis=-1, keepdims=True)
    bitangent = jnp.cross(normal, tangent)
    return jnp.stack([tangent, bitangent, normal], axis=-1)


def to_local(rotation: Float[Array, "S 3 3"], world: Float[Array, "S 3"]) -> Float[Array, "S 3"]:
    """World displacements into frame coordinates (R^T d)."""
    return jnp.einsum("sij,si->sj", rotation, world)


def to_world(rotation: Float[Array, "S 3 3"], local: Float[Array, "S 3"]) -> Float[Array, "S 3"]:
    """Frame coordinates into world displacements (R d)."""
    return jnp.einsum("sij,sj->si", rotation, local)
