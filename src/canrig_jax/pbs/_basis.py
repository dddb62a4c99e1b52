"""Patch blendshapes (PBS, CANRig section 4, eqs. 6-8): a high-resolution head as overlapping
surface patches, each a small blendshape model over one shared basis.

    S = S_neutral + W_layout S_pred S_basis                                   (eq. 7)

- **Layout** (``patch_layout``, host, once per mesh): ``n_patches`` seeds by geodesic
  farthest-point sampling on the edge graph of the parts that move, a geodesic Voronoi
  partition (multi-source Dijkstra, ``scipy.sparse.csgraph``), each cell grown by ``rings``
  vertex rings, and per-vertex weights that fall off linearly with the ring (1 in the cell,
  (rings + 1 - r) / (rings + 1) on ring r), normalised so every row of W_layout sums to 1
  (eq. 6). Geodesic, not Euclidean, distances keep a cell on one side of the lip gap and the
  eyelids: the two lips (and lids) only meet at their corners along the surface.
- **Basis** (``pbs_basis``): the neutral (the origin) and ``n_basis - 1`` extreme training
  shapes by farthest-point selection in shape space (the first: the largest offset), stored
  as offsets (B - 1, V, 3) from the neutral.
- **Fit** (``fit_pbs``): per patch, least squares over the patch's vertices for its B - 1
  weights (a small Cholesky per patch, ``jax.vmap``), then ``pbs_shape`` blends them.

The layout is kept in gather form: for every vertex, the (at most C) patches that cover it
and their weights, so that a shape is one gather and one contraction (no scatter).
``PatchLayout.matrix`` gives the same W_layout as a ``scipy.sparse`` matrix.
Units follow the mesh (ICT: cm).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Bool, Float, Float32, Int
from scipy.sparse.csgraph import dijkstra

from .._checks import check_finite, check_points, check_real, is_concrete
from .._linalg import cho_solve, cholesky, spd_solve
from ..mesh import check_mesh, edge_graph, farthest_point_vertices, vertex_adjacency


class PatchLayout(eqx.Module):
    """W_layout (N x P) in gather form.

    Attributes:
        vertex_patches: (N, C) the patches covering each vertex (padding: patch 0).
        vertex_weights: (N, C) their weights; rows sum to 1 on covered vertices, 0 elsewhere.
        seeds: (P,) the seed vertex of each patch.
        cell: (N,) each vertex's Voronoi cell (its core patch), -1 where no patch covers it.
        entries: optional (vertex, patch, weight), each (E,), the nonzero entries of W_layout
            sorted by vertex (``patch_layout`` fills them): eq. 7 then reads E entries
            instead of N x C (most vertices lie in 1-3 patches, the busiest in C).
    """

    vertex_patches: Int[Array, "N C"]
    vertex_weights: Float[Array, "N C"]
    seeds: Int[Array, " P"]
    cell: Int[Array, " N"]
    entries: tuple[Int[Array, " E"], Int[Array, " E"], Float[Array, " E"]] | None = None

    def __check_init__(self):
        patches, weights = self.vertex_patches, self.vertex_weights
        if patches.shape != weights.shape or patches.ndim != 2:
            raise ValueError(
                f"vertex_weights: expected the shape of vertex_patches {patches.shape}, "
                f"got {weights.shape}"
            )
        if not (is_concrete(weights) and is_concrete(patches)):
            return
        weights, patches = np.asarray(weights), np.asarray(patches)
        if not np.all(np.isfinite(weights)) or weights.min(initial=0) < 0:
            raise ValueError("vertex_weights: expected finite weights >= 0")
        if patches.size and (patches.min() < 0 or patches.max() >= len(self.seeds)):
            raise ValueError(f"vertex_patches: expected patch indices in [0, {len(self.seeds)})")
        sums = weights.sum(axis=1)
        bad = ~(np.isclose(sums, 1.0, atol=1e-4) | (sums == 0))
        if bad.any():
            raise ValueError(
                f"vertex_weights: rows must sum to 1 (or 0 off the patches); row "
                f"{int(np.argmax(bad))} sums to {sums[bad][0]:.6g}"
            )

    def nonzero(self) -> tuple[Int[Array, " E"], Int[Array, " E"], Float[Array, " E"]]:
        """(vertex, patch, weight) of W_layout's entries, sorted by vertex: ``entries`` when
        the layout has them, else every slot of the padded form (zero weights included)."""
        if self.entries is not None:
            return self.entries
        n, c = self.vertex_patches.shape
        vertex = jnp.repeat(jnp.arange(n, dtype=self.vertex_patches.dtype), c)
        return vertex, self.vertex_patches.reshape(-1), self.vertex_weights.reshape(-1)

    @property
    def n_patches(self) -> int:
        return int(self.seeds.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_patches.shape[0])

    def matrix(self) -> sp.csr_matrix:
        """(N, P) W_layout as a sparse matrix."""
        rows = np.repeat(np.arange(self.n_vertices), self.vertex_patches.shape[1])
        weights = np.asarray(self.vertex_weights).ravel()
        keep = weights > 0
        return sp.csr_matrix(
            (weights[keep], (rows[keep], np.asarray(self.vertex_patches).ravel()[keep])),
            shape=(self.n_vertices, self.n_patches),
        )

    def covered_by(self, patches: Bool[ArrayLike, " P"]) -> Bool[np.ndarray, " N"]:
        """(N,) the vertices that at least one of the selected ``patches`` covers."""
        patches = np.asarray(patches, bool)
        if patches.shape != (self.n_patches,):
            raise ValueError(f"patches: expected shape ({self.n_patches},), got {patches.shape}")
        covered = np.asarray(self.vertex_weights) > 0
        return np.asarray((covered & patches[np.asarray(self.vertex_patches)]).any(axis=1))

    def patch_vertices(self) -> list[Int[np.ndarray, " _"]]:
        """Per patch, the vertices it covers (its cell and rings)."""
        columns = self.matrix().tocsc()
        return [
            columns.indices[columns.indptr[p] : columns.indptr[p + 1]]
            for p in range(self.n_patches)
        ]


def _check_count(name: str, value, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name}: expected an integer, got {value!r}")
    if not low <= value <= high:
        raise ValueError(f"{name}: expected {low} <= {name} <= {high}, got {value}")
    return int(value)


def patch_layout(
    vertices: Float[ArrayLike, "N 3"],
    faces: Int[ArrayLike, "F 3"],
    n_patches: int,
    *,
    rings: int = 3,
    active: Bool[ArrayLike, " N"] | None = None,
) -> PatchLayout:
    """The patch layout of a mesh (host-side, once per mesh).

    Args:
        vertices, faces: the mesh (N vertices).
        n_patches: P, the number of patches (1 <= P <= number of active vertices).
        rings: vertex rings added around each geodesic Voronoi cell (the overlap).
        active: (N,) bool, the vertices that get patches (default all); the others are
            covered by no patch (a shape there is the neutral's).
    """
    vertices, faces = check_mesh(vertices, faces)
    n = len(vertices)
    active = np.ones(n, bool) if active is None else np.asarray(active)
    if active.shape != (n,) or active.dtype != bool:
        raise ValueError(f"active: expected a ({n},) bool mask, got {active.shape} {active.dtype}")
    n_active = int(active.sum())
    if n_active == 0:
        raise ValueError("active: selects no vertex")
    n_patches = _check_count("n_patches", n_patches, 1, n_active)
    rings = _check_count("rings", rings, 0, 64)
    # the active vertices' own graph (no edge to an inactive vertex)
    index = np.flatnonzero(active)
    keep = active[faces].all(axis=1)
    local = np.full(n, -1, np.int64)
    local[index] = np.arange(n_active)
    sub_faces = local[faces[keep]]
    if not len(sub_faces):
        raise ValueError("active: the selected vertices span no triangle")
    graph = edge_graph(vertices[index], sub_faces)
    seeds_local = farthest_point_vertices(vertices[index], n_patches, graph=graph)
    distance, _, sources = dijkstra(
        graph, directed=False, indices=seeds_local, min_only=True, return_predecessors=True
    )
    # vertices unreachable from every seed (components without one) join the nearest seed
    unreachable = ~np.isfinite(distance)
    if unreachable.any():
        euclid = np.linalg.norm(
            vertices[index][unreachable][:, None] - vertices[index][seeds_local][None], axis=-1
        )
        sources[unreachable] = seeds_local[np.argmin(euclid, axis=1)]
    seed_of = np.full(n_active, -1, np.int64)
    seed_of[seeds_local] = np.arange(n_patches)
    cell_local = seed_of[sources]
    # rings: membership grown along the adjacency; weight (rings + 1 - r) / (rings + 1)
    adjacency = vertex_adjacency(sub_faces, n_active)
    member = sp.csr_matrix(
        (np.ones(n_active), (np.arange(n_active), cell_local)), shape=(n_active, n_patches)
    )
    weight = member.astype(np.float64)
    for r in range(1, rings + 1):
        grown = sp.csr_matrix((adjacency @ member + member) > 0, dtype=np.float64)
        new = sp.csr_matrix(grown - member.astype(np.float64))
        new.eliminate_zeros()
        weight = weight + new * ((rings + 1 - r) / (rings + 1))
        member = grown
    weight = sp.csr_matrix(weight)
    # rows sum to 1
    weight = sp.csr_matrix(sp.diags(1.0 / np.asarray(weight.sum(axis=1)).ravel()) @ weight)
    counts = np.diff(weight.indptr)
    c = int(counts.max())
    patches = np.zeros((n, c), np.int32)
    weights = np.zeros((n, c), np.float32)
    slot = np.arange(len(weight.indices)) - np.repeat(weight.indptr[:-1], counts)
    rows = index[np.repeat(np.arange(n_active), counts)]
    patches[rows, slot] = weight.indices
    weights[rows, slot] = weight.data
    cell = np.full(n, -1, np.int32)
    cell[index] = cell_local
    return PatchLayout(
        vertex_patches=jnp.asarray(patches),
        vertex_weights=jnp.asarray(weights),
        seeds=jnp.asarray(index[seeds_local].astype(np.int32)),
        cell=jnp.asarray(cell),
        entries=(
            jnp.asarray(rows.astype(np.int32)),
            jnp.asarray(weight.indices.astype(np.int32)),
            jnp.asarray(weight.data.astype(np.float32)),
        ),
    )


def pbs_basis(
    neutral: Float[ArrayLike, "N 3"], shapes: Float[ArrayLike, "M N 3"], n_basis: int = 19
) -> tuple[Float32[np.ndarray, "Bm1 N 3"], Int[np.ndarray, " Bm1"]]:
    """(offsets (n_basis - 1, N, 3), indices into ``shapes``): the neutral is the basis's
    origin and the other n_basis - 1 are extreme shapes by farthest-point selection in shape
    space (Euclidean over all coordinates), starting from the largest offset."""
    neutral = np.asarray(neutral, np.float64)
    shapes = np.asarray(shapes, np.float64)
    if shapes.ndim != 3 or shapes.shape[1:] != neutral.shape:
        raise ValueError(f"shapes: expected (M, {len(neutral)}, 3), got {shapes.shape}")
    if not np.all(np.isfinite(shapes)):
        raise ValueError("shapes: expected finite values")
    n_basis = _check_count("n_basis", n_basis, 2, len(shapes) + 1)
    offsets = (shapes - neutral).reshape(len(shapes), -1)
    norms = np.linalg.norm(offsets, axis=1)
    chosen = [int(np.argmax(norms))]
    nearest = np.linalg.norm(offsets - offsets[chosen[0]], axis=1)
    nearest = np.minimum(nearest, norms)  # the neutral is in the basis too
    for _ in range(n_basis - 2):
        pick = int(np.argmax(nearest))
        if nearest[pick] <= 0:
            raise ValueError("shapes: fewer distinct non-neutral shapes than n_basis - 1")
        chosen.append(pick)
        nearest = np.minimum(nearest, np.linalg.norm(offsets - offsets[pick], axis=1))
    index = np.array(chosen)
    return (shapes[index] - neutral).astype(np.float32), index


def check_basis(basis: Float[ArrayLike, "B N 3"], n_vertices: int) -> Float32[Array, "B N 3"]:
    """A basis of offsets: finite, (B, N, 3), no all-zero and no repeated shape."""
    basis = np.asarray(basis, np.float32)
    if basis.ndim != 3 or basis.shape[1:] != (n_vertices, 3) or len(basis) == 0:
        raise ValueError(f"basis: expected (B, {n_vertices}, 3), got {basis.shape}")
    if not np.all(np.isfinite(basis)):
        raise ValueError("basis: expected finite offsets")
    flat = basis.reshape(len(basis), -1)
    norms = np.linalg.norm(flat, axis=1)
    if np.any(norms == 0):
        raise ValueError(f"basis: shape {int(np.argmin(norms))} is all zero")
    gram = flat @ flat.T / np.outer(norms, norms)
    np.fill_diagonal(gram, 0.0)
    if np.any(gram > 1 - 1e-6):
        i, j = np.unravel_index(int(np.argmax(gram)), gram.shape)
        raise ValueError(f"basis: shapes {min(i, j)} and {max(i, j)} are the same up to scale")
    return jnp.asarray(basis)


def _check_points(name: str, x: ArrayLike, n_vertices: int, batch: bool = False) -> None:
    """``check_points`` for (V, 3), or with ``batch`` any leading axes (..., V, 3)."""
    shape = np.shape(x)
    if batch and len(shape) > 2:
        x = np.reshape(x, (-1, *shape[-2:]))
    check_points(name, x, n_vertices, frames=batch and len(shape) > 2)


def pbs_shape(
    layout: PatchLayout,
    neutral: Float[ArrayLike, "N 3"],
    basis: Float[ArrayLike, "B N 3"],
    weights: Float[ArrayLike, "*F P B"],
) -> Float[Array, "*F N 3"]:
    """S = S_neutral + W_layout S_pred S_basis (eq. 7) in gather form, for any leading batch
    of ``weights`` (P, B); zero weights give the neutral exactly. Validated, then jitted."""
    _check_points("neutral", neutral, layout.n_vertices)
    _check_points("basis", basis, layout.n_vertices, batch=True)
    check_real("weights", weights)
    b = np.shape(basis)[0]
    if np.ndim(basis) != 3 or tuple(np.shape(weights)[-2:]) != (layout.n_patches, b):
        raise ValueError(
            f"weights: expected shape (..., {layout.n_patches}, {b}), got {np.shape(weights)}"
        )
    check_finite("weights", weights)
    core = _pbs_shape
    for _ in range(np.ndim(weights) - 2):
        core = jax.vmap(core, (None, None, None, 0))
    return core(layout, jnp.asarray(neutral), jnp.asarray(basis), jnp.asarray(weights))


@jax.jit
def _pbs_shape(
    layout: PatchLayout,
    neutral: Float[Array, "N 3"],
    basis: Float[Array, "B N 3"],
    weights: Float[Array, "P B"],
) -> Float[Array, "N 3"]:
    """S = S_neutral + W_layout S_pred S_basis (eq. 7) over W_layout's entries
    (``PatchLayout.nonzero``); zero weights give the neutral exactly."""
    vertex, patch, weight = layout.nonzero()
    blended = jax.ops.segment_sum(
        weight[:, None] * weights[patch],
        vertex,
        num_segments=neutral.shape[0],
        indices_are_sorted=True,
    )
    return neutral + jnp.einsum("nb,bnk->nk", blended, basis)


def fit_pbs(
    layout: PatchLayout,
    neutral: Float[ArrayLike, "N 3"],
    basis: Float[ArrayLike, "B N 3"],
    shape: Float[ArrayLike, "*F N 3"],
    ridge: float = 1e-4,
) -> Float[Array, "*F P B"]:
    """Per-patch least squares (``_fit_pbs``) of one shape or a batch (leading axes of
    ``shape``). Validated, then jitted."""
    _check_points("neutral", neutral, layout.n_vertices)
    _check_points("basis", basis, layout.n_vertices, batch=True)
    _check_points("shape", shape, layout.n_vertices, batch=True)
    if np.ndim(basis) != 3:
        raise ValueError(f"basis: expected (B, {layout.n_vertices}, 3), got {np.shape(basis)}")
    if not (np.isfinite(ridge) and ridge >= 0):
        raise ValueError(f"ridge: expected a finite value >= 0, got {ridge}")
    core = _fit_pbs
    for _ in range(np.ndim(shape) - 2):
        core = jax.vmap(core, (None, None, None, 0, None))
    return core(layout, jnp.asarray(neutral), jnp.asarray(basis), jnp.asarray(shape), ridge)


@jax.jit
def _fit_pbs(
    layout: PatchLayout,
    neutral: Float[Array, "N 3"],
    basis: Float[Array, "B N 3"],
    shape: Float[Array, "N 3"],
    ridge: float | Float[Array, ""] = 1e-4,
) -> Float[Array, "P B"]:
    """Per-patch least squares: for each patch, the B weights minimising
    sum_v w_vp ||sum_b x_b basis[b, v] - (shape - neutral)[v]||^2 over the vertices it covers
    (w_vp its layout weight), plus ``ridge`` x the mean diagonal ||x||^2 (a patch where the
    basis does not move stays finite). One (B x B) Cholesky solve per patch."""
    p = layout.seeds.shape[0]
    # normal equations per patch: sum_v w_vp a_v a_v^T, a_v the (B, 3) basis at v
    per_vertex_gram = jnp.einsum("bnk,cnk->nbc", basis, basis)  # (N, B, B)
    per_vertex_rhs = jnp.einsum("bnk,nk->nb", basis, shape - neutral)  # (N, B)
    weights = layout.vertex_weights  # (N, C)
    gram = jax.ops.segment_sum(
        (weights[..., None, None] * per_vertex_gram[:, None]).reshape(
            -1, *per_vertex_gram.shape[1:]
        ),
        layout.vertex_patches.reshape(-1),
        num_segments=p,
    )
    rhs = jax.ops.segment_sum(
        (weights[..., None] * per_vertex_rhs[:, None]).reshape(-1, per_vertex_rhs.shape[1]),
        layout.vertex_patches.reshape(-1),
        num_segments=p,
    )
    scale = jnp.mean(jnp.diagonal(gram, axis1=1, axis2=2), axis=1)  # (P,)
    eye = jnp.eye(gram.shape[1], dtype=gram.dtype)
    regular = gram + (ridge * scale + 1e-12)[:, None, None] * eye
    return cho_solve(cholesky(regular), rhs)


def local_pbs_fit(
    handle_basis: Float[ArrayLike, "Bm1 H 3"],
    displacements: Float[ArrayLike, "*F H 3"],
    mask: Float[ArrayLike, "P H"],
    ridge: float = 1e-2,
) -> Float[Array, "*F P Bm1"]:
    """``_local_pbs_fit`` for one set of handle displacements or a batch, validated."""
    handle_basis = np.asarray(handle_basis)
    if handle_basis.ndim != 3 or handle_basis.shape[2] != 3:
        raise ValueError(f"handle_basis: expected (B - 1, H, 3), got {handle_basis.shape}")
    n_handles = handle_basis.shape[1]
    check_finite("handle_basis", handle_basis)
    _check_points("displacements", displacements, n_handles, batch=True)
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.shape[1] != n_handles:
        raise ValueError(f"mask: expected (P, {n_handles}), got {mask.shape}")
    if not (np.isfinite(mask).all() and (mask >= 0).all()):
        raise ValueError("mask: expected finite values >= 0")
    if not (np.isfinite(ridge) and ridge > 0):
        raise ValueError(f"ridge: expected a finite value > 0, got {ridge}")
    core = _local_pbs_fit
    for _ in range(np.ndim(displacements) - 2):
        core = jax.vmap(core, (None, 0, None, None))
    return core(jnp.asarray(handle_basis), jnp.asarray(displacements), jnp.asarray(mask), ridge)


@jax.jit
def _local_pbs_fit(
    handle_basis: Float[Array, "Bm1 H 3"],
    displacements: Float[Array, "H 3"],
    mask: Float[Array, "P H"],
    ridge: float | Float[Array, ""] = 1e-2,
) -> Float[Array, "P Bm1"]:
    """Each patch's PBS weights fitted to the handles it sees (beyond the paper; CANRig-PBS's
    ``local_prior``): for patch p the x minimising

        sum_h M_ph ||handle_basis[:, h]^T x - d_h||^2 + ridge * s * ||x||^2,

    with s = the basis's mean squared offset per handle and coordinate (one constant for the
    edit, so a patch that its handles reach weakly is shrunk towards zero, and its weights
    fade as the masks do). Linear in the displacements (zero displacements give exactly zero
    weights) and exactly zero for a patch every mask misses (M_p = 0). One (B-1) x (B-1)
    Cholesky solve per patch; jit/vmap/grad-safe (also in ``ridge``)."""
    factor = local_fit_factor(handle_basis, mask, ridge)
    return local_fit_solve(factor, handle_basis, mask, displacements)


def local_fit_factor(
    handle_basis: Float[Array, "Bm1 H 3"],
    mask: Float[Array, "P H"],
    ridge: float | Float[Array, ""],
) -> tuple[Float[Array, "P Bm1 Bm1"], Bool[Array, " P"]]:
    """The Cholesky factors of ``_local_pbs_fit``'s normal matrices (they do not depend on
    the displacements: factor once, solve for many) and which of them succeeded. A float32
    factorisation can fail on a normal matrix that rounding left not positive definite (not
    seen on real edits); that patch gets the identity and ``ok`` False, and
    ``local_fit_solve`` gives it zero weights, never NaN."""
    gram = jnp.einsum("ph,bhk,chk->pbc", mask, handle_basis, handle_basis)
    scale = jnp.mean(handle_basis**2) * 3.0 + 1e-12
    eye = jnp.eye(gram.shape[1], dtype=gram.dtype)
    factor = cholesky(gram + (ridge * scale) * eye)
    ok = jnp.all(jnp.isfinite(factor), axis=(1, 2))
    return jnp.where(ok[:, None, None], factor, eye), ok


def local_fit_solve(
    factors: tuple[Float[Array, "P Bm1 Bm1"], Bool[Array, " P"]],
    handle_basis: Float[Array, "Bm1 H 3"],
    mask: Float[Array, "P H"],
    displacements: Float[Array, "H 3"],
) -> Float[Array, "P Bm1"]:
    """``_local_pbs_fit`` with the factors of ``local_fit_factor``: linear in d (zero for a
    patch whose factorisation failed)."""
    factor, ok = factors
    weighted = mask * ok[:, None]
    return cho_solve(factor, jnp.einsum("ph,bhk,hk->pb", weighted, handle_basis, displacements))


def check_handle_index(
    handle_index: Int[ArrayLike, " H"], n_vertices: int
) -> Int[np.ndarray, " H"]:
    """``handle_index`` as (H,) distinct integer vertex indices in [0, ``n_vertices``), else
    ValueError naming it."""
    index = np.asarray(handle_index)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        raise ValueError(f"handle_index: expected (H,) integer vertex indices, got {index.dtype}")
    if index.size == 0 or index.min() < 0 or index.max() >= n_vertices:
        raise ValueError(f"handle_index: expected indices in [0, {n_vertices})")
    if len(np.unique(index)) != len(index):
        raise ValueError("handle_index: repeated vertices")
    return index


def global_blendshape_fit(
    basis: Float[ArrayLike, "B N 3"],
    handle_index: Int[ArrayLike, " H"],
    displacements: Float[ArrayLike, "*F H 3"],
    ridge: float = 1e-3,
) -> Float[Array, "*F B"]:
    """``_global_blendshape_fit`` for one set of handle displacements or a batch, validated."""
    basis = np.asarray(basis)
    if basis.ndim != 3 or basis.shape[2] != 3:
        raise ValueError(f"basis: expected (B, N, 3), got {basis.shape}")
    index = check_handle_index(handle_index, basis.shape[1])
    _check_points("displacements", displacements, len(index), batch=True)
    if not (np.isfinite(ridge) and ridge > 0):
        raise ValueError(f"ridge: expected a finite value > 0, got {ridge}")
    core = _global_blendshape_fit
    for _ in range(np.ndim(displacements) - 2):
        core = jax.vmap(core, (None, None, 0, None))
    return core(jnp.asarray(basis), jnp.asarray(index), jnp.asarray(displacements), ridge)


@jax.jit
def _global_blendshape_fit(
    basis: Float[Array, "B N 3"],
    handle_index: Int[Array, " H"],
    displacements: Float[Array, "H 3"],
    ridge: float | Float[Array, ""] = 1e-3,
) -> Float[Array, " B"]:
    """The global-blendshape baseline (GBS, CANRig Tables 5-6): the basis weights whose
    offsets best match ``displacements`` at the handle vertices, by regularised least squares
    (``ridge`` x the mean diagonal of the normal matrix), applied to the whole mesh with
    ``basis`` (weights @ basis)."""
    at_handles = basis[:, handle_index].reshape(basis.shape[0], -1)  # (B, 3H)
    gram = at_handles @ at_handles.T
    scale = jnp.mean(jnp.diagonal(gram)) + 1e-12
    matrix = gram + ridge * scale * jnp.eye(gram.shape[0], dtype=gram.dtype)
    return spd_solve(matrix, at_handles @ displacements.reshape(-1))


def global_blendshape_dialogue(
    basis: Float[ArrayLike, "B N 3"],
    neutral: Float[ArrayLike, "N 3"],
    source: Float[ArrayLike, "F N 3"],
    target: Float[ArrayLike, "F N 3"],
    handle_index: Int[ArrayLike, " H"],
    moved: Bool[ArrayLike, " H"],
    ridge: float = 1e-3,
) -> tuple[Float[Array, "F N 3"], Float[Array, "F N 3"]]:
    """Dialogue replacement with global blendshapes (the GBS row of CANRig's Table 6).

    A global rig has no base shape, so each source frame is first inverted: the weights
    fitted to its positions at every handle (``global_blendshape_fit``); then the ``moved``
    handles (bool (H,), e.g. those on the mouth) take the target frame's positions, the
    others keep the source's, and the weights are fitted again. Returns (inverted, edited),
    both (F, N, 3) in the mesh's units: ``inverted`` against ``source`` is the rig-inversion
    error, ``edited`` the replaced clip (its change outside the mouth is what a global basis
    leaks)."""
    neutral = check_points("neutral", neutral, np.shape(basis)[1])
    source = check_points("source", source, len(neutral), frames=True)
    target = check_points("target", target, len(neutral), frames=True)
    if source.shape != target.shape:
        raise ValueError(f"target: expected the source's shape {source.shape}, got {target.shape}")
    index = np.asarray(handle_index)
    moved = np.asarray(moved)
    if moved.dtype != bool or moved.shape != index.shape:
        raise ValueError(f"moved: expected a bool mask of shape {index.shape}, got {moved.dtype}")
    rest = neutral[index]
    edited_handles = np.where(moved[None, :, None], target[:, index], source[:, index])
    weights = global_blendshape_fit(
        basis, index, np.stack([source[:, index], edited_handles]) - rest, ridge
    )  # (2, F, B)
    shapes = neutral + jnp.einsum("kfb,bnc->kfnc", weights, jnp.asarray(basis))
    return shapes[0], shapes[1]
