"""Mesh operators for learning on surfaces, computed once per mesh and cached on disk.

DiffusionNet (Sharp et al. 2022) splits geometry from layers: everything a layer needs from a
mesh is precomputed here, on the host (NumPy / SciPy), and the layers in
``canrig_jax.autorig`` only consume it.

* Laplacian L (positive semi-definite "weak" cotangent Laplacian) and lumped mass M from
  ``robust_laplacian.mesh_laplacian`` (Sharp & Crane 2020): built on the intrinsic tufted
  cover with a mollified intrinsic Delaunay triangulation, so non-manifold edges, duplicated
  positions and zero-area triangles give finite, positive weights (a naive cotangent would
  produce NaN or negative weights there).
* A truncated eigenbasis of the generalised problem L phi = lambda M phi, M-orthonormal
  (phi^T M phi = I), solved per connected component in standard form (dense LAPACK for small
  parts, shift-invert Lanczos, ``scipy.sparse.linalg.eigsh``, for large ones). There is one
  zero eigenvalue per connected component, its eigenvector the constant on that component.
* Per-vertex tangent frames (area-weighted normal, a tangent from the world x axis projected
  on the tangent plane, falling back to y) and two sparse gradient operators: the components
  of a function's gradient in each vertex's frame, fitted by least squares to the edges at
  that vertex (DiffusionNet's construction).

Isolated vertices (in no face) are a documented repair, not an error: they get zero mass, no
Laplacian entries, zero eigenvector rows and zero gradients, and are reported in
``MeshGeometry.isolated_vertices``; diffusion leaves them at zero.

``mesh_geometry`` returns the host ``MeshGeometry``; ``MeshOperators.from_geometry`` turns it
into the JAX pytree the layers take; ``mesh_operators`` does both. Results are cached in
``cache_dir()`` keyed by a SHA-256 of the vertices, faces and parameters.
"""

import dataclasses
import hashlib
import os
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.csgraph
import scipy.sparse.linalg as spla
from jaxtyping import Array, ArrayLike, DTypeLike, Float, Int, Shaped

from .._cache import cache_dir, mesh_fingerprint
from .._io import save_npz
from ._checks import check_mesh, sparse_shape
from ._topology import connected_components

OPERATORS_VERSION = 2
"""Bump when the operators change, to invalidate caches."""

DENSE_EIGEN_MAX_SMALL = 256
DENSE_EIGEN_MAX = 3000
"""Which connected blocks ``eigenbasis`` solves densely (see ``_block_eigenpairs``)."""

ZERO_EIGENVALUE_TOL = 1e-6
"""An eigenvalue is 'zero' when lambda * (total surface area) < this (scale-free)."""


# --------------------------------------------------------------------------------------------
# Host-side geometry
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeshGeometry:
    """Operators of one mesh as host arrays (float64), cached on disk.

    Attributes:
        vertices: (V, 3) positions; faces: (F, 3) triangles.
        laplacian: (V, V) sparse symmetric PSD weak Laplacian L (rows sum to zero).
        mass: (V,) lumped mass (vertex area; 0 for isolated vertices).
        eigenvalues: (k,) ascending, of L phi = lambda M phi (zero ones set to exactly 0).
        eigenvectors: (V, k) M-orthonormal.
        frames: (V, 3, 3) per-vertex [tangent x, tangent y, normal] as rows.
        gradient_x, gradient_y: (V, V) sparse; (gradient_x @ f)[i] is the component of the
            gradient of f along frames[i, 0], likewise y.
        n_components: connected components of the faces (isolated vertices not counted).
        n_zero_eigenvalues: eigenvalues with lambda * total_area < ZERO_EIGENVALUE_TOL.
        isolated_vertices: vertices in no face (zero mass; repaired, not an error).
        n_degenerate_faces: faces of zero area (handled by robust-laplacian's mollification).
        seconds: time to compute (not to load).
        from_cache: whether this came from the disk cache.
    """

    vertices: Float[np.ndarray, "V 3"]
    faces: Int[np.ndarray, "F 3"]
    laplacian: sp.csr_matrix
    mass: Float[np.ndarray, " V"]
    eigenvalues: Float[np.ndarray, " k"]
    eigenvectors: Float[np.ndarray, "V k"]
    frames: Float[np.ndarray, "V 3 3"]
    gradient_x: sp.csr_matrix
    gradient_y: sp.csr_matrix
    n_components: int
    n_zero_eigenvalues: int
    isolated_vertices: Int[np.ndarray, " I"]
    n_degenerate_faces: int
    seconds: float
    from_cache: bool = False

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def k(self) -> int:
        return int(self.eigenvalues.shape[0])

    @property
    def total_area(self) -> float:
        return float(self.mass.sum())


def laplacian_and_mass(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], mollify_factor: float = 1e-5
) -> tuple[sp.csr_matrix, Float[np.ndarray, " V"], Int[np.ndarray, " I"]]:
    """Robust weak Laplacian (V, V), lumped mass (V,) and the isolated vertices.

    Isolated vertices are excluded from robust-laplacian's construction and get an empty row
    and column and zero mass.
    """
    import robust_laplacian

    vertices, faces = check_mesh(vertices, faces)
    n = vertices.shape[0]
    used = np.zeros(n, bool)
    used[faces.ravel()] = True
    isolated = np.flatnonzero(~used)
    if isolated.size:
        keep = np.flatnonzero(used)
        new_index = np.full(n, -1, np.int64)
        new_index[keep] = np.arange(keep.size)
        sub_l, sub_m = robust_laplacian.mesh_laplacian(
            np.ascontiguousarray(vertices[keep]), new_index[faces], mollify_factor
        )
        embed = sp.csr_matrix((np.ones(keep.size), (keep, np.arange(keep.size))), (n, keep.size))
        laplacian = (embed @ sp.csr_matrix(sub_l) @ embed.T).tocsr()
        mass = np.zeros(n)
        mass[keep] = sub_m.diagonal()
    else:
        laplacian, m = robust_laplacian.mesh_laplacian(vertices, faces, mollify_factor)
        laplacian, mass = sp.csr_matrix(laplacian), np.asarray(m.diagonal(), np.float64)
    return laplacian, mass, isolated


def _block_eigenpairs(block: sp.csr_matrix, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k smallest eigenpairs of one connected symmetric PSD block (standard form).

    Dense LAPACK when the block has at most ``DENSE_EIGEN_MAX_SMALL`` vertices, or at most
    ``DENSE_EIGEN_MAX`` with k at least 1/8 of them (there the O(n^3) reduction costs less
    than shift-invert Lanczos); shift-invert Lanczos near a tiny negative shift otherwise (the
    block is singular: constants are in its null space)."""
    n = sparse_shape(block)[0]
    dense = n <= DENSE_EIGEN_MAX_SMALL or (n <= DENSE_EIGEN_MAX and 8 * k >= n) or k >= n - 1
    if not dense:
        shift = 1e-8 * block.diagonal().sum() / n
        values, vectors = spla.eigsh(block.tocsc(), k=k, sigma=-shift)
        order = np.argsort(values)
        return values[order], vectors[:, order]
    # scipy's LAPACK throughout: numpy's bundled OpenBLAS has its own thread pool, whose
    # spinning threads slow the next scipy call by half on 2 cores
    options = dict(overwrite_a=True, check_finite=False)
    if 2 * k >= n:  # most of the spectrum: all of it by divide and conquer is cheaper
        values, vectors = scipy.linalg.eigh(block.toarray(), driver="evd", **options)
        return values[:k], vectors[:, :k]
    return scipy.linalg.eigh(block.toarray(), subset_by_index=[0, k - 1], driver="evr", **options)


def eigenbasis(
    laplacian: sp.spmatrix, mass: Float[ArrayLike, " V"], k: int
) -> tuple[Float[np.ndarray, " k"], Float[np.ndarray, "V k"]]:
    """The k smallest eigenpairs of L phi = lambda M phi, M-orthonormal, ascending.

    With M diagonal this is the standard problem A psi = lambda psi, A = M^-1/2 L M^-1/2,
    phi = M^-1/2 psi. A is block diagonal over the mesh's connected components (a head: skin,
    eyeballs, teeth, ... 56 parts at 1,750 vertices), so each block is solved on its own (at
    most k pairs each) and the k smallest of the union are kept: the same eigenpairs as one
    solve of the whole matrix, each zero eigenvector the constant on one component. Vertices
    with zero mass (isolated) are left out and get zero rows. Ties are broken by component
    order (stable sort).
    """
    mass = np.asarray(mass)
    n = mass.shape[0]
    eigenvectors = np.zeros((n, k))
    if k == 0:
        return np.zeros(0), eigenvectors
    active = np.flatnonzero(mass > 0)
    if k > active.size:
        raise ValueError(f"k: at most {active.size} eigenpairs exist for this mesh, asked for {k}")
    sub = sp.csr_matrix(laplacian)[active][:, active]
    n_blocks, labels = scipy.sparse.csgraph.connected_components(sub, directed=False)
    order = np.argsort(labels, kind="stable")  # vertices (of `active`) grouped by block
    sizes = np.bincount(labels, minlength=n_blocks)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    scale = 1.0 / np.sqrt(mass[active][order])
    standard = sp.csr_matrix(sp.diags(scale) @ sub[order][:, order] @ sp.diags(scale))
    values, vectors = zip(
        *(
            _block_eigenpairs(standard[a : a + size, a : a + size], min(k, int(size)))
            for a, size in zip(starts[:-1], sizes, strict=True)
        ),
        strict=True,
    )
    owner = np.repeat(np.arange(n_blocks), [v.size for v in values])
    column = np.concatenate([np.arange(v.size) for v in values])
    keep = np.argsort(np.concatenate(values), kind="stable")[:k]
    rows = active[order]
    for j, (b, c) in enumerate(zip(owner[keep], column[keep], strict=True)):
        span = slice(starts[b], starts[b + 1])
        eigenvectors[rows[span], j] = vectors[b][:, c] * scale[span]
    return np.concatenate(values)[keep], eigenvectors


def vertex_normals(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[np.ndarray, "V 3"]:
    """(V, 3) unit area-weighted vertex normals; +z where undefined (isolated, degenerate)."""
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    cross = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    normals = np.zeros_like(vertices)
    for j in range(3):
        np.add.at(normals, faces[:, j], cross)
    length = np.linalg.norm(normals, axis=1)
    bad = length < 1e-12 * max(1.0, float(np.abs(vertices).max()) ** 2)
    normals[bad] = (0.0, 0.0, 1.0)
    length[bad] = 1.0
    return normals / length[:, None]


def tangent_frames(normals: Float[ArrayLike, "V 3"]) -> Float[np.ndarray, "V 3 3"]:
    """(V, 3, 3) right-handed frames [x, y, n] (rows): x is world x projected on the
    tangent plane (world y where the normal is within ~25 degrees of x), y = n cross x."""
    normals = np.asarray(normals)
    candidate = np.tile(np.array([1.0, 0.0, 0.0]), (normals.shape[0], 1))
    near = np.abs(normals[:, 0]) > 0.9
    candidate[near] = (0.0, 1.0, 0.0)
    x_axis = candidate - np.sum(candidate * normals, axis=1, keepdims=True) * normals
    x_axis /= np.linalg.norm(x_axis, axis=1, keepdims=True)
    y_axis = np.cross(normals, x_axis)
    return np.stack([x_axis, y_axis, normals], axis=1)


def gradient_operators(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    frames: Float[ArrayLike, "V 3 3"],
    regularization: float = 1e-5,
) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse (V, V) operators giving each vertex's gradient components in its frame.

    At vertex i with neighbours j, the edges e_ij = x_j - x_i are expressed in the tangent
    frame, E_i (n_i, 2), and the gradient g_i solves the regularised least squares
    min ||E_i g - (f_j - f_i)||^2 + eps ||g||^2, eps = ``regularization`` times the mean
    squared edge length at i (scale-free): g_i = (E_i^T E_i + eps I)^{-1} E_i^T (f_N - f_i).
    """
    vertices, faces, frames = np.asarray(vertices), np.asarray(faces), np.asarray(frames)
    n = vertices.shape[0]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    keys = np.unique(edges[:, 0] * n + edges[:, 1])  # the directed edges, sorted by (src, dst)
    src, dst = keys // n, keys % n
    src, dst = src[src != dst], dst[src != dst]
    vec = vertices[dst] - vertices[src]
    local = np.stack(
        [np.sum(vec * frames[src, 0], axis=1), np.sum(vec * frames[src, 1], axis=1)], axis=1
    )  # (E, 2)
    gram = np.zeros((n, 2, 2))
    np.add.at(gram, src, local[:, :, None] * local[:, None, :])
    count = np.bincount(src, minlength=n)
    mean_sq = np.zeros(n)
    np.add.at(mean_sq, src, np.sum(vec**2, axis=1))
    mean_sq = np.where(count > 0, mean_sq / np.maximum(count, 1), 1.0)
    gram += (regularization * mean_sq)[:, None, None] * np.eye(2)
    coefficient = np.einsum("eab,eb->ea", np.linalg.inv(gram)[src], local)  # (E, 2)
    rows = np.concatenate([src, src])
    cols = np.concatenate([dst, src])
    out = []
    for axis in range(2):
        values = np.concatenate([coefficient[:, axis], -coefficient[:, axis]])
        out.append(sp.csr_matrix((values, (rows, cols)), shape=(n, n)))
    return out[0], out[1]


def compute_geometry(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    k: int = 128,
    mollify_factor: float = 1e-5,
) -> MeshGeometry:
    """All operators of one mesh, without the cache. See the module docstring."""
    start = time.perf_counter()
    vertices, faces = check_mesh(vertices, faces)
    if not isinstance(k, int | np.integer) or k < 0:
        raise ValueError(f"k: expected a non-negative integer number of eigenpairs, got {k!r}")
    if not (np.isfinite(mollify_factor) and mollify_factor >= 0):
        raise ValueError(f"mollify_factor: expected a finite value >= 0, got {mollify_factor}")
    twice_area = np.linalg.norm(
        np.cross(
            vertices[faces[:, 1]] - vertices[faces[:, 0]],
            vertices[faces[:, 2]] - vertices[faces[:, 0]],
        ),
        axis=1,
    )
    extent = float(np.ptp(vertices, axis=0).max())
    if not np.any(twice_area > 1e-12 * max(extent, 1e-30) ** 2):
        raise ValueError(
            "faces: every triangle has zero area (the vertices are collinear or coincide); "
            "a surface needs at least one proper triangle"
        )
    laplacian, mass, isolated = laplacian_and_mass(vertices, faces, mollify_factor)
    values, vectors = eigenbasis(laplacian, mass, k)
    total_area = mass.sum()
    zero = np.abs(values) * total_area < ZERO_EIGENVALUE_TOL
    values = np.where(zero, 0.0, values)
    frames = tangent_frames(vertex_normals(vertices, faces))
    gradient_x, gradient_y = gradient_operators(vertices, faces, frames)
    labels = connected_components(faces, vertices.shape[0])
    n_components = np.unique(labels[np.setdiff1d(np.arange(len(labels)), isolated)]).size
    cross = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    return MeshGeometry(
        vertices=vertices,
        faces=faces,
        laplacian=laplacian,
        mass=mass,
        eigenvalues=values,
        eigenvectors=vectors,
        frames=frames,
        gradient_x=gradient_x,
        gradient_y=gradient_y,
        n_components=int(n_components),
        n_zero_eigenvalues=int(zero.sum()),
        isolated_vertices=isolated,
        n_degenerate_faces=int(np.sum(np.linalg.norm(cross, axis=1) == 0.0)),
        seconds=time.perf_counter() - start,
    )


def _sparse_to_arrays(prefix: str, matrix: sp.spmatrix) -> dict[str, np.ndarray]:
    coo = sp.coo_matrix(matrix)
    return {f"{prefix}_rows": coo.row, f"{prefix}_cols": coo.col, f"{prefix}_values": coo.data}


def _sparse_from_arrays(z, prefix: str, n: int) -> sp.csr_matrix:
    return sp.csr_matrix(
        (z[f"{prefix}_values"], (z[f"{prefix}_rows"], z[f"{prefix}_cols"])), shape=(n, n)
    )


def geometry_cache_key(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], k: int, mollify_factor: float
) -> str:
    """Cache key: SHA-256 of the mesh (float64 vertices, int64 faces) and the parameters."""
    vertices, faces = check_mesh(vertices, faces)
    recipe = f"{mesh_fingerprint(vertices, faces)}k{k}m{mollify_factor!r}v{OPERATORS_VERSION}"
    return hashlib.sha256(recipe.encode()).hexdigest()[:24]


def mesh_geometry(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    k: int = 128,
    mollify_factor: float = 1e-5,
    cache: str | os.PathLike | bool | None = None,
) -> MeshGeometry:
    """Operators of one mesh, from the disk cache when present (a few milliseconds).

    Args:
        vertices: (V, 3) positions; faces: (F, 3) triangles.
        k: eigenpairs to keep (0 for none: implicit diffusion only).
        mollify_factor: robust-laplacian's intrinsic mollification, relative to mean edge length.
        cache: a folder, ``None`` for ``cache_dir()`` (``$CANRIG_CACHE`` or
            ``~/.cache/canrig_jax``), or ``False`` to neither read nor write.
    """
    vertices, faces = check_mesh(vertices, faces)
    if cache is False:
        return compute_geometry(vertices, faces, k=k, mollify_factor=mollify_factor)
    folder = cache_dir(None if cache is None or cache is True else cache)
    path = folder / f"operators-{geometry_cache_key(vertices, faces, k, mollify_factor)}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as z:
            n = int(vertices.shape[0])
            return MeshGeometry(
                vertices=vertices,
                faces=faces,
                laplacian=_sparse_from_arrays(z, "laplacian", n),
                mass=z["mass"],
                eigenvalues=z["eigenvalues"],
                eigenvectors=z["eigenvectors"],
                frames=z["frames"],
                gradient_x=_sparse_from_arrays(z, "gradient_x", n),
                gradient_y=_sparse_from_arrays(z, "gradient_y", n),
                n_components=int(z["n_components"]),
                n_zero_eigenvalues=int(z["n_zero_eigenvalues"]),
                isolated_vertices=z["isolated_vertices"],
                n_degenerate_faces=int(z["n_degenerate_faces"]),
                seconds=float(z["seconds"]),
                from_cache=True,
            )
    geometry = compute_geometry(vertices, faces, k=k, mollify_factor=mollify_factor)
    save_npz(
        path,
        mass=geometry.mass,
        eigenvalues=geometry.eigenvalues,
        eigenvectors=geometry.eigenvectors,
        frames=geometry.frames,
        n_components=geometry.n_components,
        n_zero_eigenvalues=geometry.n_zero_eigenvalues,
        isolated_vertices=geometry.isolated_vertices,
        n_degenerate_faces=geometry.n_degenerate_faces,
        seconds=geometry.seconds,
        **_sparse_to_arrays("laplacian", geometry.laplacian),
        **_sparse_to_arrays("gradient_x", geometry.gradient_x),
        **_sparse_to_arrays("gradient_y", geometry.gradient_y),
    )
    return geometry


# --------------------------------------------------------------------------------------------
# Device-side operators (the pytree the layers consume)
# --------------------------------------------------------------------------------------------


class SparseMatrix(eqx.Module):
    """A square sparse matrix in coordinate form, multiplied with ``segment_sum``
    (jit-, vmap- and grad-safe). Padding entries have value 0 and point at row/col 0."""

    rows: Int[Array, " nnz"]
    cols: Int[Array, " nnz"]
    values: Float[Array, " nnz"]

    def __call__(self, x: Float[Array, "V ..."]) -> Float[Array, "V ..."]:
        gathered = x[self.cols] * self.values.reshape((-1,) + (1,) * (x.ndim - 1))
        return jax.ops.segment_sum(gathered, self.rows, num_segments=x.shape[0])

    def diagonal(self, n: int) -> Float[Array, " V"]:
        on_diagonal = jnp.where(self.rows == self.cols, self.values, 0.0)
        return jax.ops.segment_sum(on_diagonal, self.rows, num_segments=n)

    @classmethod
    def from_scipy(cls, matrix: sp.spmatrix, dtype: DTypeLike = jnp.float32) -> "SparseMatrix":
        coo = sp.coo_matrix(matrix)
        return cls(
            jnp.asarray(coo.row, jnp.int32),
            jnp.asarray(coo.col, jnp.int32),
            jnp.asarray(coo.data, dtype),
        )

    def pad(self, nnz: int) -> "SparseMatrix":
        extra = nnz - self.values.shape[0]
        if extra < 0:
            raise ValueError(f"nnz: cannot pad {self.values.shape[0]} entries down to {nnz}")
        zeros = jnp.zeros(extra, jnp.int32)
        return SparseMatrix(
            jnp.concatenate([self.rows, zeros]),
            jnp.concatenate([self.cols, zeros]),
            jnp.concatenate([self.values, jnp.zeros(extra, self.values.dtype)]),
        )


class MeshOperators(eqx.Module):
    """Everything a DiffusionNet layer needs from one mesh, as JAX arrays (float32).

    Batching meshes of different sizes is by **padding**: ``stack_operators`` pads every mesh
    to the largest vertex, face, eigenpair and non-zero counts and stacks them, and
    ``eqx.filter_vmap`` maps a model over the stack. Padded vertices have ``vertex_mask`` 0,
    zero mass, zero eigenvector rows and no operator entries, so they neither receive nor
    send anything; padded faces have ``face_mask`` 0 and point at vertex 0.

    Attributes:
        mass: (V,) lumped mass; eigenvalues: (k,); eigenvectors: (V, k), M-orthonormal.
        laplacian, gradient_x, gradient_y: ``SparseMatrix`` (V, V).
        eigenvector_gradients: (V, k, 2) the gradient operators applied to the eigenvectors,
            so the gradient of a spectrally diffused function Phi c is a dense product
            (G Phi) c instead of a sparse gather over every channel.
        frames: (V, 3, 3) tangent frames [x, y, normal] (rows).
        faces: (F, 3) int32; vertex_mask: (V,); face_mask: (F,) (1 real, 0 padding/isolated).
    """

    mass: Float[Array, " V"]
    eigenvalues: Float[Array, " k"]
    eigenvectors: Float[Array, "V k"]
    laplacian: SparseMatrix
    gradient_x: SparseMatrix
    gradient_y: SparseMatrix
    eigenvector_gradients: Float[Array, "V k 2"]
    frames: Float[Array, "V 3 3"]
    faces: Int[Array, "F 3"]
    vertex_mask: Float[Array, " V"]
    face_mask: Float[Array, " F"]

    @classmethod
    def from_geometry(
        cls, geometry: MeshGeometry, dtype: DTypeLike = jnp.float32
    ) -> "MeshOperators":
        f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        return cls(
            mass=f(geometry.mass),
            eigenvalues=f(geometry.eigenvalues),
            eigenvectors=f(geometry.eigenvectors),
            laplacian=SparseMatrix.from_scipy(geometry.laplacian, dtype),
            gradient_x=SparseMatrix.from_scipy(geometry.gradient_x, dtype),
            gradient_y=SparseMatrix.from_scipy(geometry.gradient_y, dtype),
            eigenvector_gradients=f(
                np.stack(
                    [
                        geometry.gradient_x @ geometry.eigenvectors,
                        geometry.gradient_y @ geometry.eigenvectors,
                    ],
                    axis=-1,
                )
            ),
            frames=f(geometry.frames),
            faces=jnp.asarray(geometry.faces, jnp.int32),
            vertex_mask=f(geometry.mass > 0),
            face_mask=jnp.ones(geometry.faces.shape[0], dtype),
        )

    @property
    def n_vertices(self) -> int:
        return int(self.mass.shape[-1])

    def pad(self, n_vertices: int, n_faces: int, k: int, nnz: dict[str, int]) -> "MeshOperators":
        """The same operators padded to ``n_vertices``, ``n_faces``, ``k`` eigenpairs and
        ``nnz[name]`` entries for each sparse matrix (padded eigenpairs: value 0, vector 0)."""
        v, f, kk = self.mass.shape[0], self.faces.shape[0], self.eigenvalues.shape[0]
        if n_vertices < v or n_faces < f or k < kk:
            raise ValueError(
                f"n_vertices, n_faces, k: cannot pad ({v}, {f}, {kk}) down to "
                f"({n_vertices}, {n_faces}, {k})"
            )
        dv, df, dk = n_vertices - v, n_faces - f, k - kk
        return MeshOperators(
            mass=jnp.pad(self.mass, (0, dv)),
            eigenvalues=jnp.pad(self.eigenvalues, (0, dk)),
            eigenvectors=jnp.pad(self.eigenvectors, ((0, dv), (0, dk))),
            laplacian=self.laplacian.pad(nnz["laplacian"]),
            gradient_x=self.gradient_x.pad(nnz["gradient_x"]),
            gradient_y=self.gradient_y.pad(nnz["gradient_y"]),
            eigenvector_gradients=jnp.pad(self.eigenvector_gradients, ((0, dv), (0, dk), (0, 0))),
            frames=jnp.pad(self.frames, ((0, dv), (0, 0), (0, 0))),
            faces=jnp.pad(self.faces, ((0, df), (0, 0))),
            vertex_mask=jnp.pad(self.vertex_mask, (0, dv)),
            face_mask=jnp.pad(self.face_mask, (0, df)),
        )


_SPARSE = ("laplacian", "gradient_x", "gradient_y")


def stack_operators(operators: list[MeshOperators]) -> MeshOperators:
    """Pad meshes of different sizes to a common size and stack them on a leading axis.

    Map a model over the result with ``eqx.filter_vmap(model)(features, stacked)``, features
    padded to the same vertex count (``pad_vertices``); read mesh i's output back as
    ``out[i, :n_vertices_i]``.
    """
    if not operators:
        raise ValueError("operators: expected at least one mesh")
    n_vertices = max(o.mass.shape[0] for o in operators)
    n_faces = max(o.faces.shape[0] for o in operators)
    k = max(o.eigenvalues.shape[0] for o in operators)
    nnz = {name: max(getattr(o, name).values.shape[0] for o in operators) for name in _SPARSE}
    padded = [o.pad(n_vertices, n_faces, k, nnz) for o in operators]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *padded)


def pad_vertices(
    values: Sequence[Shaped[ArrayLike, " _ *rest"]], n_vertices: int | None = None
) -> Shaped[Array, "B V *rest"]:
    """Stack per-vertex arrays (V_i, ...) of different lengths, zero-padded to (B, V, ...).

    ``n_vertices`` (default: the longest V_i) must be at least every V_i. Raises ValueError
    naming ``values`` for no arrays, arrays without a vertex axis or of different trailing
    shapes, and ``n_vertices`` when it is shorter than one of them."""
    values = list(values)
    if not values:
        raise ValueError("values: no arrays to stack (an empty list); pass at least one")
    shapes = [np.shape(v) for v in values]
    if any(len(s) == 0 for s in shapes):
        raise ValueError(f"values: every array needs a vertex axis, got shapes {shapes}")
    if len({s[1:] for s in shapes}) > 1:
        raise ValueError(f"values: arrays differ beyond the vertex axis: shapes {shapes}")
    longest = max(s[0] for s in shapes)
    n_vertices = n_vertices or longest
    if n_vertices < longest:
        raise ValueError(f"n_vertices: {n_vertices} is shorter than the longest array ({longest})")
    return jnp.stack(
        [
            jnp.pad(
                jnp.asarray(v), [(0, n_vertices - np.shape(v)[0])] + [(0, 0)] * (np.ndim(v) - 1)
            )
            for v in values
        ]
    )


def mesh_operators(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    k: int = 128,
    mollify_factor: float = 1e-5,
    cache: str | os.PathLike | bool | None = None,
) -> MeshOperators:
    """``MeshOperators.from_geometry(mesh_geometry(...))``: cached operators as a pytree."""
    return MeshOperators.from_geometry(
        mesh_geometry(vertices, faces, k=k, mollify_factor=mollify_factor, cache=cache)
    )
