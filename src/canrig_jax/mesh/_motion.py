"""Mesh quality under motion: what a rigger looks for frame by frame — triangles turned
inside out, edges crossing other triangles (self-intersections), stretched edges — and how
rigidly a part moved (the residual of its best rigid fit).

Frames are (T, V, 3) positions of one mesh (any unit; the counts are unitless). All of it is
vectorised over frames: NumPy on the host, and the intersection test compiled over the
candidate pairs of a KD-tree."""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float64, Int
from scipy.spatial import cKDTree

from ._geodesic import mesh_edges


def _frames(frames, n_vertices: int | None = None) -> np.ndarray:
    x = np.asarray(frames, np.float64)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 3 or (n_vertices is not None and x.shape[1] != n_vertices):
        want = f"(T, {n_vertices}, 3)" if n_vertices is not None else "(T, V, 3)"
        raise ValueError(f"frames: expected {want} positions, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("frames: contains non-finite positions")
    return x


def _face_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (x[..., faces[:, i], :] for i in range(3))
    return np.cross(b - a, c - a)


def flipped_triangles(
    frames: Float[ArrayLike, "T V 3"],
    neutral: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    mask: Bool[ArrayLike, " F"] | None = None,
) -> Bool[np.ndarray, "T F"]:
    """(T, F) bool: triangle f's normal in frame t points against its neutral normal (turned
    inside out). Degenerate neutral triangles (zero area) are never counted. ``mask`` (F,)
    restricts the count to some triangles (e.g. the skin's)."""
    neutral = np.asarray(neutral, np.float64)
    faces = np.asarray(faces, np.int64)
    x = _frames(frames, neutral.shape[0])
    n0 = _face_normals(neutral, faces)
    area0 = np.linalg.norm(n0, axis=-1)
    keep = area0 > 1e-12 * max(float(area0.max()), 1e-30)
    if mask is not None:
        keep &= np.asarray(mask, bool)
    index = np.flatnonzero(keep)
    kept, normals = faces[index], n0[index]
    out = np.zeros((x.shape[0], len(faces)), bool)
    for start in range(0, x.shape[0], 32):  # 32 frames at a time: the temporaries stay small
        now = _face_normals(x[start : start + 32], kept)
        out[start : start + 32, index] = np.einsum("tfc,fc->tf", now, normals) < 0
    return out


def edge_stretch(
    frames: Float[ArrayLike, "T V 3"],
    neutral: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
) -> Float64[np.ndarray, "T E"]:
    """(T, E) each unique edge's length over its neutral length (1: unchanged; > 1 stretched,
    < 1 compressed), edges in ``np.unique`` order of their sorted vertex pairs. Zero-length
    neutral edges (seams) are left out."""
    neutral = np.asarray(neutral, np.float64)
    edges = mesh_edges(faces)
    x = _frames(frames, neutral.shape[0])
    rest = np.linalg.norm(neutral[edges[:, 1]] - neutral[edges[:, 0]], axis=-1)
    keep = rest > 1e-9 * max(float(rest.max()), 1e-30)
    head, tail = edges[keep, 1], edges[keep, 0]
    now = np.concatenate(  # 32 frames at a time: the temporaries stay small
        [np.linalg.norm(x[s : s + 32, head] - x[s : s + 32, tail], axis=-1)
         for s in range(0, x.shape[0], 32)]
    )  # fmt: skip
    return now / rest[keep]


MOTION_BOUND_FRAMES = 64
"""``self_intersections`` bounds each pair's relative motion first (``_could_meet``) from
this many frames on; the bound costs about as much as testing every pair in this many
frames."""


def self_intersections(
    frames: Float[ArrayLike, "T V 3"],
    neutral: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    mask: Bool[ArrayLike, " F"] | None = None,
    near: float = 0.5,
) -> Int[np.ndarray, " T"]:
    """(T,) how many (edge, triangle) pairs cross in each frame that did not cross in the
    neutral: an edge passes through a triangle it shares no vertex with (the lips through each
    other, a lid through the other lid). ``mask`` (F,) limits the triangles (and their edges)
    tested, e.g. to the skin; a part crossing another part is not counted.

    The pairs tested are those near each other in the neutral (their bounding spheres closer
    than their radii plus ``near`` times the median edge length: lips, lids, folds; a KD-tree),
    each exactly in every frame (segment against triangle, Möller-Trumbore; compiled, frame by
    frame). A surface that travels further than that to cross another is not seen."""
    neutral = _frames(neutral)[0]
    faces = np.asarray(faces, np.int64)
    if mask is not None:
        faces = faces[np.asarray(mask, bool)]
    x = _frames(frames, neutral.shape[0])
    if len(faces) == 0:
        return np.zeros(x.shape[0], np.int64)
    edges = mesh_edges(faces)
    tri = neutral[faces]
    tri_centre = tri.mean(axis=1)
    tri_size = np.linalg.norm(tri - tri_centre[:, None], axis=-1).max(axis=1)
    seg_centre = neutral[edges].mean(axis=1)
    seg_length = np.linalg.norm(neutral[edges[:, 1]] - neutral[edges[:, 0]], axis=-1)
    seg_size = 0.5 * seg_length + near * float(np.median(seg_length))
    e_all, f_all = [], []
    tri_index = np.arange(len(faces))
    for f_bin, f_reach in _size_bins(tri_index, tri_size):
        tree = cKDTree(tri_centre[f_bin])
        for e_bin, e_reach in _size_bins(np.arange(len(edges)), seg_size):
            pairs = cKDTree(seg_centre[e_bin]).sparse_distance_matrix(
                tree, f_reach + e_reach, output_type="ndarray"
            )
            e_all.append(e_bin[pairs["i"]])
            f_all.append(f_bin[pairs["j"]])
    e, f = np.concatenate(e_all), np.concatenate(f_all)
    # a segment's (a triangle's) points move no further than its farthest-moving corner; a
    # pair of which nothing moves keeps its neutral relation
    reach = np.linalg.norm(x - neutral, axis=-1).max(axis=0)  # (V,)
    moves = (reach[edges[e]].max(axis=1) > 0) | (reach[faces[f]].max(axis=1) > 0)
    e, f = e[moves], f[moves]
    keep = ~(edges[e, :, None] == faces[f, None, :]).any(axis=(1, 2))
    keep &= np.linalg.norm(seg_centre[e] - tri_centre[f], axis=-1) <= seg_size[e] + tri_size[f]
    e, f = e[keep], f[keep]
    before = _segment_crosses_triangle(neutral[edges[e]], neutral[faces[f]])
    e, f = e[~before], f[~before]
    # a pair can cross only if its points move towards each other by their neutral gap
    gap = np.linalg.norm(seg_centre[e] - tri_centre[f], axis=-1) - 0.5 * seg_length[e]
    movable = gap - tri_size[f] <= reach[edges[e]].max(axis=1) + reach[faces[f]].max(axis=1)
    e, f = e[movable], f[movable]
    if x.shape[0] >= MOTION_BOUND_FRAMES:  # fewer frames: the exact test costs less
        meet = _could_meet(neutral, x, edges[e], faces[f])
        e, f = e[meet], f[meet]
    if e.size == 0:
        return np.zeros(x.shape[0], np.int64)
    # one compiled shape per size class of the pair list (padded with a pair that cannot cross)
    n = 1 << int(np.ceil(np.log2(e.size)))
    seg_vertices = np.zeros((n, 2), np.int32)
    tri_vertices = np.zeros((n, 3), np.int32)
    seg_vertices[: e.size], tri_vertices[: e.size] = edges[e], faces[f]
    tri_vertices[e.size :] = seg_vertices[e.size :, :1]  # shares a vertex: never crosses
    valid = np.arange(n) < e.size
    return np.asarray(
        _count_crossings(jnp.asarray(x, jnp.float32), seg_vertices, tri_vertices, valid)
    ).astype(np.int64)


def _could_meet(neutral: np.ndarray, x: np.ndarray, seg: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) bool: segment n (vertices ``seg[n]``) and triangle n (``tri[n]``), apart in the
    neutral, may meet in some frame of ``x``: two points meet only when their relative
    motion covers their neutral distance, and the relative motion of a point of the segment
    and one of the triangle is at most the largest of the six relative motions of their
    vertices (both are convex combinations). The neutral distance is bounded below by the
    largest gap along seven separating axes (the triangle's normal, its edges' in-plane
    normals, the segment's direction across each edge): False only where they cannot meet."""
    p = neutral[seg]  # (N, 2, 3)
    t = neutral[tri]  # (N, 3, 3)
    edge = t[:, [1, 2, 0]] - t  # (N, 3, 3)
    normal = np.cross(edge[:, 0], edge[:, 1])
    axes = np.concatenate(
        [normal[:, None], np.cross(normal[:, None], edge), np.cross(p[:, 1:] - p[:, :1], edge)], 1
    )  # (N, 7, 3)
    axes /= np.maximum(np.linalg.norm(axes, axis=-1, keepdims=True), 1e-30)
    on_seg = np.einsum("nkc,njc->nkj", axes, p)
    on_tri = np.einsum("nkc,njc->nkj", axes, t)
    gap = np.maximum(on_seg.min(-1) - on_tri.max(-1), on_tri.min(-1) - on_seg.max(-1))
    gap = np.maximum(gap.max(-1), 0.0)  # (N,): at most the neutral distance
    # the largest relative motion of a vertex pair, over the frames, each pair once
    key = np.repeat(seg, 3, axis=1).astype(np.int64) * len(neutral) + np.tile(tri, (1, 2))
    unique, where = np.unique(key.reshape(-1), return_inverse=True)
    first, second = np.divmod(unique, len(neutral))
    motion = np.zeros(len(unique))
    for start in range(0, x.shape[0], 32):
        d = x[start : start + 32] - neutral
        step = np.linalg.norm(d[:, first] - d[:, second], axis=-1).max(axis=0)
        motion = np.maximum(motion, step)
    reach = motion[where.reshape(-1)].reshape(-1, 6).max(axis=1)
    return reach >= gap * (1 - 1e-6)


@jax.jit
def _count_crossings(x, seg_vertices, tri_vertices, valid):
    def one(frame):
        crossing = _segment_crosses_triangle(frame[seg_vertices], frame[tri_vertices], jnp)
        return jnp.sum(crossing & valid)

    return jax.lax.map(one, x)


def _size_bins(index: np.ndarray, radius: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """``index`` split by size, a bin per factor of 2 of ``radius``: [(indices, largest
    radius in the bin)]."""
    scale = max(float(radius.max()), 1e-30)
    level = np.clip(np.floor(np.log2(np.maximum(radius, 1e-30) / scale)), -6, 0).astype(int)
    return [(index[level == k], float(radius[level == k].max())) for k in np.unique(level)]


def _segment_crosses_triangle(seg, tri, xp=np):
    """(N,) bool: segment n (2, 3) crosses triangle n (3, 3) strictly inside both (NumPy,
    or ``xp=jax.numpy``)."""
    p, q = seg[:, 0], seg[:, 1]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    direction = q - p
    e1, e2 = b - a, c - a
    h = xp.cross(direction, e2)
    det = (e1 * h).sum(-1)
    scale = xp.linalg.norm(e1, axis=-1) * xp.linalg.norm(e2, axis=-1)
    scale = scale * xp.linalg.norm(direction, axis=-1)
    ok = xp.abs(det) > 1e-6 * scale
    inv = xp.where(ok, 1.0 / xp.where(ok, det, 1.0), 0.0)
    s = p - a
    u = inv * (s * h).sum(-1)
    qv = xp.cross(s, e1)
    v = inv * (direction * qv).sum(-1)
    t = inv * (e2 * qv).sum(-1)
    eps = 1e-6
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def rigid_residual(
    rest: Float[ArrayLike, "N 3"], moved: Float[ArrayLike, "*batch N 3"]
) -> Float64[np.ndarray, " *batch"]:
    """The RMS distance (units of the points) between ``moved`` and the best rigid motion
    (rotation and translation, Kabsch) of ``rest``: 0 for a part that moved rigidly."""
    rest = np.asarray(rest, np.float64)
    moved = np.asarray(moved, np.float64)
    if rest.ndim != 2 or rest.shape[-1] != 3 or moved.shape[-2:] != rest.shape:
        raise ValueError(
            f"rest, moved: expected (N, 3) and (..., N, 3), got {rest.shape}, {moved.shape}"
        )
    a = rest - rest.mean(axis=0)
    b = moved - moved.mean(axis=-2, keepdims=True)
    u, _, vt = np.linalg.svd(np.einsum("ni,...nj->...ij", a, b))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, -1] *= d[..., None]
    rotation = u @ vt  # a @ rotation ~ b
    fitted = np.einsum("ni,...ij->...nj", a, rotation)
    return np.asarray(np.sqrt(((fitted - b) ** 2).sum(axis=-1).mean(axis=-1)))
