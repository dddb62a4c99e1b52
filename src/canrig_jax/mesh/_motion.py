"""Mesh quality under motion: what a rigger looks for frame by frame — triangles turned
inside out, edges crossing other triangles (self-intersections), stretched edges — and how
rigidly a part moved (the residual of its best rigid fit).

Frames are (T, V, 3) positions of one mesh (any unit; the counts are unitless). All of it is
vectorised over frames: NumPy on the host, and the intersection test compiled over the
candidate pairs of a KD-tree."""

import collections
import dataclasses
import hashlib

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


CROSSING_FRAMES_PER_STEP = 8
"""Frames ``_count_crossings`` tests at once (one fused loop over pairs and frames; some 10 ns
a pair and frame on a CPU core, less than a bound on each pair's motion over the frames
would cost to leave pairs out)."""


@dataclasses.dataclass(frozen=True)
class _NearPairs:
    """The broad phase of ``self_intersections`` on one neutral mesh, what every set of frames
    shares: the (edge, triangle) pairs near each other that share no vertex and do not cross
    in the neutral, with the sizes the motion filters read."""

    edges: Int[np.ndarray, "E 2"]
    faces: Int[np.ndarray, "F 3"]
    e: Int[np.ndarray, " N"]
    f: Int[np.ndarray, " N"]
    seg_centre: Float64[np.ndarray, "E 3"]
    seg_length: Float64[np.ndarray, " E"]
    tri_centre: Float64[np.ndarray, "F 3"]
    tri_size: Float64[np.ndarray, " F"]


_NEAR_PAIRS: collections.OrderedDict[bytes, _NearPairs] = collections.OrderedDict()
_NEAR_PAIRS_KEPT = 8


def _near_pairs(neutral: np.ndarray, faces: np.ndarray, near: float) -> _NearPairs:
    """``_build_near_pairs``, built once per (neutral, faces, near) content and kept for the
    last ``_NEAR_PAIRS_KEPT`` meshes (the blink's fit and the rig's checks test one neutral)."""
    digest = hashlib.blake2b(neutral.tobytes(), digest_size=16)
    digest.update(faces.tobytes())
    key = digest.digest() + repr((neutral.shape, faces.shape, float(near))).encode()
    pairs = _NEAR_PAIRS.pop(key, None) or _build_near_pairs(neutral, faces, near)
    _NEAR_PAIRS[key] = pairs
    while len(_NEAR_PAIRS) > _NEAR_PAIRS_KEPT:
        _NEAR_PAIRS.popitem(last=False)
    return pairs


def _build_near_pairs(neutral: np.ndarray, faces: np.ndarray, near: float) -> _NearPairs:
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
    keep = ~(edges[e, :, None] == faces[f, None, :]).any(axis=(1, 2))
    keep &= np.linalg.norm(seg_centre[e] - tri_centre[f], axis=-1) <= seg_size[e] + tri_size[f]
    e, f = e[keep], f[keep]
    before = _segment_crosses_triangle(neutral[edges[e]], neutral[faces[f]])
    e, f = e[~before], f[~before]
    for a in (edges, faces, e, f, seg_centre, seg_length, tri_centre, tri_size):
        a.setflags(write=False)
    return _NearPairs(edges, faces, e, f, seg_centre, seg_length, tri_centre, tri_size)


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
    than their radii plus ``near`` times the median edge length: lips, lids, folds; a KD-tree,
    built once per neutral and kept for the next call), each exactly in every frame (segment
    against triangle, Möller-Trumbore; compiled, a few frames at a time). A surface that
    travels further than that to cross another is not seen."""
    neutral = _frames(neutral)[0]
    faces = np.asarray(faces, np.int64)
    if mask is not None:
        faces = faces[np.asarray(mask, bool)]
    x = _frames(frames, neutral.shape[0])
    if len(faces) == 0:
        return np.zeros(x.shape[0], np.int64)
    near_pairs = _near_pairs(neutral, np.ascontiguousarray(faces), near)
    edges, faces, e, f = near_pairs.edges, near_pairs.faces, near_pairs.e, near_pairs.f
    # a segment's (a triangle's) points move no further than its farthest-moving corner; a
    # pair of which nothing moves keeps its neutral relation
    reach = np.linalg.norm(x - neutral, axis=-1).max(axis=0)  # (V,)
    seg_reach, tri_reach = reach[edges[e]].max(axis=1), reach[faces[f]].max(axis=1)
    # a pair can cross only if its points move towards each other by their neutral gap
    gap = np.linalg.norm(near_pairs.seg_centre[e] - near_pairs.tri_centre[f], axis=-1)
    gap -= 0.5 * near_pairs.seg_length[e]
    movable = ((seg_reach > 0) | (tri_reach > 0)) & (
        gap - near_pairs.tri_size[f] <= seg_reach + tri_reach
    )
    e, f = e[movable], f[movable]
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


@jax.jit
def _count_crossings(x, seg_vertices, tri_vertices, valid):
    """(T,) crossing pairs per frame of ``x`` (T, V, 3): every pair's corners gathered
    coordinate by coordinate, so that the test is one fused loop over the pairs of
    ``CROSSING_FRAMES_PER_STEP`` frames (no per-pair (3,) temporaries)."""

    def one(coords):  # (3, V): a frame's x, y and z
        def corner(index):
            return tuple(coords[k][index] for k in range(3))

        crossing = _crosses(
            corner(seg_vertices[:, 0]), corner(seg_vertices[:, 1]),
            corner(tri_vertices[:, 0]), corner(tri_vertices[:, 1]), corner(tri_vertices[:, 2]),
            jnp,
        )  # fmt: skip
        return jnp.sum(crossing & valid)

    return jax.lax.map(one, jnp.swapaxes(x, 1, 2), batch_size=CROSSING_FRAMES_PER_STEP)


def _size_bins(index: np.ndarray, radius: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """``index`` split by size, a bin per factor of 2 of ``radius``: [(indices, largest
    radius in the bin)]."""
    scale = max(float(radius.max()), 1e-30)
    level = np.clip(np.floor(np.log2(np.maximum(radius, 1e-30) / scale)), -6, 0).astype(int)
    return [(index[level == k], float(radius[level == k].max())) for k in np.unique(level)]


def _segment_crosses_triangle(seg, tri, xp=np):
    """(N,) bool: segment n (2, 3) crosses triangle n (3, 3) strictly inside both (NumPy,
    or ``xp=jax.numpy``)."""
    corner = lambda a, i: tuple(a[:, i, k] for k in range(3))  # noqa: E731
    return _crosses(
        corner(seg, 0), corner(seg, 1), corner(tri, 0), corner(tri, 1), corner(tri, 2), xp
    )


def _crosses(p, q, a, b, c, xp):
    """Segment p-q crosses triangle a-b-c strictly inside both (Möller-Trumbore): each
    point a tuple of its x, y, z arrays (any shape), NumPy or ``xp=jax.numpy``. The sums of
    three products in the order of ``(x * y).sum(-1)``."""

    def minus(u, v):
        return (u[0] - v[0], u[1] - v[1], u[2] - v[2])

    def dot(u, v):
        return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

    def cross(u, v):
        return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])

    direction = minus(q, p)
    e1, e2 = minus(b, a), minus(c, a)
    h = cross(direction, e2)
    det = dot(e1, h)
    scale = xp.sqrt(dot(e1, e1)) * xp.sqrt(dot(e2, e2))
    scale = scale * xp.sqrt(dot(direction, direction))
    ok = xp.abs(det) > 1e-6 * scale
    inv = xp.where(ok, 1.0 / xp.where(ok, det, 1.0), 0.0)
    s = minus(p, a)
    u = inv * dot(s, h)
    qv = cross(s, e1)
    v = inv * dot(direction, qv)
    t = inv * dot(e2, qv)
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
