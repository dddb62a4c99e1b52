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

Run-time layout (what makes the frames cheap on a CPU): each used triangle's normal is
computed once; the vertices are grouped by their number of incident triangles (neighbouring
degrees merged into one group where that saves more operations than the padding costs,
padding pointing at an exact zero normal), and each group sums its triangles' normals with
one row gather per ring slot, no weights; a final gather puts the vertices back in order.
The normalisation, tangent and bitangent are written per coordinate, so XLA fuses them.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int


class LocalFrames(eqx.Module):
    """Topology needed to build frames at ``vertices`` of a mesh.

    Attributes:
        vertices: (S,) vertices that get a frame.
        faces: (T, 3) the triangles incident to any of them (normals are computed once each).
        incident: (S, D) rows of ``faces`` incident to each vertex, padded by repeating one.
        weight: (S, D) 1 for a real incident triangle, 0 for padding.
        neighbour: (S,) the neighbour whose edge gives the tangent.
        rings: the same incident rows grouped by vertex degree (the run-time layout): one
            (S_g, d_g) array per group of vertices of degree at most d_g (in increasing
            vertex order), a vertex's slots past its degree pointing at row T (a zero normal).
        ring_order: (S,) row of each vertex of ``vertices`` in the concatenated ``rings``.
    """

    vertices: Int[Array, " S"]
    faces: Int[Array, "T 3"]
    incident: Int[Array, "S D"]
    weight: Float[Array, "S D"]
    neighbour: Int[Array, " S"]
    rings: tuple[Int[Array, "_ _"], ...]
    ring_order: Int[Array, " S"]

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
    # the next corner of the vertex's first triangle (a fixed neighbour along an edge)
    first = corner[:, 0]
    neighbour = faces[first // 3, (first % 3 + 1) % 3] if vertices.size else vertices
    used, incident = np.unique(face_index, return_inverse=True)
    incident = incident.reshape(face_index.shape)
    real = np.arange(width)[None, :] < degree[:, None]
    weight = real.astype(np.float32)
    padded = np.where(real, incident, len(used))  # past the degree: the zero normal
    rings, members = [], []
    for low, high in _degree_groups(degree):
        group = np.flatnonzero((degree >= low) & (degree <= high))
        rings.append(jnp.asarray(padded[group, :high], jnp.int32))
        members.append(group)
    ring_order = np.empty(len(vertices), np.int64)
    ring_order[np.concatenate(members or [np.zeros(0, np.int64)])] = np.arange(len(vertices))
    return LocalFrames(
        jnp.asarray(vertices, jnp.int32),
        jnp.asarray(faces[used].reshape(-1, 3), jnp.int32),
        jnp.asarray(incident, jnp.int32),
        jnp.asarray(weight),
        jnp.asarray(neighbour, jnp.int32),
        tuple(rings),
        jnp.asarray(ring_order, jnp.int32),
    )


GROUP_COST = 4096
"""Cost of one more ring group (a gather-sum loop of its own), in padded gather slots; a
rough CPU figure, it only decides which neighbouring degrees share a group."""


def _degree_groups(degree: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous ranges (low, high) of the distinct degrees minimising the padded slots
    (vertices x widest degree, per group) plus ``GROUP_COST`` per group (dynamic programme)."""
    values, counts = np.unique(degree, return_counts=True)
    best = [0.0] + [np.inf] * len(values)
    start = [0] * (len(values) + 1)
    for j in range(1, len(values) + 1):
        for i in range(j):
            cost = best[i] + counts[i:j].sum() * values[j - 1] + GROUP_COST
            if cost < best[j]:
                best[j], start[j] = cost, i
    groups, j = [], len(values)
    while j > 0:
        groups.append((int(values[start[j]]), int(values[j - 1])))
        j = start[j]
    return groups[::-1]


def _gather(x, index):
    return x.at[index].get(mode="promise_in_bounds")


def _coordinates(x):
    return x[:, 0], x[:, 1], x[:, 2]


def _cross(a, b):
    (ax, ay, az), (bx, by, bz) = a, b
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def _frame_axes(frames: LocalFrames, posed: Float[Array, "V 3"]):
    """Tangent, bitangent and normal at ``frames.vertices``, each a tuple of three (S,)
    coordinate arrays (x, y, z)."""
    posed = jnp.asarray(posed)
    p0, p1, p2 = (_gather(posed, frames.faces[:, j]) for j in range(3))
    face_normal = jnp.cross(p1 - p0, p2 - p0)  # (T, 3), twice the area, once per triangle
    face_normal = jnp.concatenate([face_normal, jnp.zeros((1, 3), face_normal.dtype)])
    sums = []
    for ring in frames.rings:  # vertices of degree <= d: d row gathers, summed
        total = _gather(face_normal, ring[:, 0])
        for k in range(1, ring.shape[1]):
            total = total + _gather(face_normal, ring[:, k])
        sums.append(total)
    if sums:
        normal = _gather(jnp.concatenate(sums), frames.ring_order)
    else:
        normal = jnp.zeros((0, 3), posed.dtype)
    nx, ny, nz = _coordinates(normal)
    scale = jax.lax.rsqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx * scale, ny * scale, nz * scale
    tip = _coordinates(_gather(posed, frames.neighbour))
    base = _coordinates(_gather(posed, frames.vertices))
    ex, ey, ez = (a - b for a, b in zip(tip, base, strict=True))
    along = ex * nx + ey * ny + ez * nz
    tx, ty, tz = ex - along * nx, ey - along * ny, ez - along * nz
    scale = jax.lax.rsqrt(tx * tx + ty * ty + tz * tz)
    tangent = (tx * scale, ty * scale, tz * scale)
    normal = (nx, ny, nz)
    return tangent, _cross(normal, tangent), normal


def frame_matrices(frames: LocalFrames, posed: Float[ArrayLike, "V 3"]) -> Float[Array, "S 3 3"]:
    """(S, 3, 3) orthonormal frames; columns are tangent, bitangent, normal in world space."""
    posed = jnp.asarray(posed)
    return jnp.stack([jnp.stack(axis, axis=-1) for axis in _frame_axes(frames, posed)], axis=-1)


def local_to_world(
    frames: LocalFrames, posed: Float[ArrayLike, "V 3"], local: Float[ArrayLike, "S 3"]
) -> Float[Array, "S 3"]:
    """Frame coordinates at ``frames.vertices`` of the mesh ``posed`` into world offsets
    (``to_world(frame_matrices(...), local)`` without forming the matrices)."""
    posed = jnp.asarray(posed)
    tangent, bitangent, normal = _frame_axes(frames, posed)
    a, b, c = _coordinates(jnp.asarray(local))
    return jnp.stack(
        [a * t + b * u + c * n for t, u, n in zip(tangent, bitangent, normal, strict=True)],
        axis=-1,
    )


def to_local(rotation: Float[Array, "S 3 3"], world: Float[Array, "S 3"]) -> Float[Array, "S 3"]:
    """World displacements into frame coordinates (R^T d)."""
    return jnp.einsum("sij,si->sj", rotation, world)


def to_world(rotation: Float[Array, "S 3 3"], local: Float[Array, "S 3"]) -> Float[Array, "S 3"]:
    """Frame coordinates into world displacements (R d)."""
    return jnp.einsum("sij,sj->si", rotation, local)
