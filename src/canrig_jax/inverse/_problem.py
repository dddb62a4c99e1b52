"""The inverse-rig problem in coefficient space.

Every mesh the rig produces is b0 + M a(w), where the columns of M are the K blendshape
offsets followed by the C corrective offsets (all orders), and a(w) = [w, prod of weights of
each combination]. With the Gram matrix Q = M^T M (P x P, P = K + C) and the projection
p = M^T (b - b0) of a target b, the objective of Racković et al. 2023,

    E(w) = 1/2 ||f(w) - b||^2 + alpha 1^T w = 1/2 (a^T Q a - 2 a^T p + ||b - b0||^2) + alpha 1^T w,

and every coordinate update need only P-vectors, never a 3V-vector: f is affine in each single
weight, a(w) = a(w with w_i = 0) + w_i g_i(w), and phi_i = M g_i.
"""

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._warnings import warn
from ..rig import BlendshapeRig, Corrective, combination_coefficients
from ._points import points_rig


class InverseProblem(eqx.Module):
    """A rig prepared for inversion (computed once per rig by ``prepare``).

    Attributes:
        neutral: (V, 3) rest mesh.
        columns: (P, 3V) float32 the columns of M (blendshapes then correctives), one per
            row: the projection M^T (b - b0) is then a row-major matrix-vector product
            (XLA's CPU kernel for ``basis.T @ x`` on a (3V, P) array was 25x slower, and it
            was most of the one-frame latency).
        gram: (P, P) float32 Q = M^T M, accumulated in float64.
        combinations: one (C_n, n) index table per corrective order, in column order of M.
        blendshape_norms: (K,) ||b_i||, used to order coordinates.
        pseudoinverse: (K, 3V) float32 B^+ of the linear blendshape matrix, computed in
            float64 (the linear Gram matrix of ICT is too ill-conditioned for float32).
        pair_hessian_bounds: (3V, 3) for every mesh coordinate k, the smallest and largest
            eigenvalue and the spectral norm of the K x K pair-corrective Hessian block
            H_k (H_k[i, j] = H_k[j, i] = b^{ij}_k / 2), for LMMM's majoriser.
        support: (K, m) int32 the columns of M that depend on weight i: i itself first, then
            every combination containing i (padded with column i, marked invalid).
        support_others: (K, m, n) int32 for each of those columns, the other weights of the
            combination (padded with K, which stands for a weight of 1).
        support_valid: (K, m) bool, False on padding.
        support_gram: (K, m, P) float32 rows Q[support_i, :], zero on padding: coordinate
            descent updates the gradient Q a - p with one of these blocks per coordinate.
        support_block: (K, m, m) float32 Q[support_i, support_i], zero on padding.
        rig: the rig itself, for solvers that call ``evaluate`` directly.
        linear_term: optional (P,) vector added to every projection, and
        constant_term: optional scalar added to every objective: how a quadratic penalty
            on the weights with a linear part (``Constrained``'s temporal term
            lambda / 2 ||w - w_prev||^2) enters the problem a method solves; None (the
            default, as ``prepare`` leaves them) adds nothing.
    """

    neutral: Float[Array, "V 3"]
    columns: Float[Array, "P N"]
    gram: Float[Array, "P P"]
    combinations: tuple[Int[Array, "_C _order"], ...]
    blendshape_norms: Float[Array, " K"]
    pseudoinverse: Float[Array, "K N"]
    pair_hessian_bounds: Float[Array, "N 3"]
    support: Int[Array, "K m"]
    support_others: Int[Array, "K m n"]
    support_valid: Bool[Array, "K m"]
    support_gram: Float[Array, "K m P"]
    support_block: Float[Array, "K m m"]
    rig: BlendshapeRig
    linear_term: Float[Array, " P"] | None = None
    constant_term: Float[Array, ""] | None = None

    @property
    def n_blendshapes(self) -> int:
        return int(self.blendshape_norms.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    def coefficients(self, weights: Float[Array, " K"]) -> Float[Array, " P"]:
        """a(w) = [w, product of the weights of each combination]."""
        return jnp.concatenate(
            [weights, *(combination_coefficients(weights, c) for c in self.combinations)]
        )

    def slopes(self, weights: Float[Array, " K"]) -> Float[Array, "K m"]:
        """(K, m) d a / d w_i on the support of each weight i: the product of the other
        weights of each combination (1 for column i itself), 0 on padding."""
        extended = jnp.append(weights, jnp.ones((1,), weights.dtype))
        slope = jnp.prod(extended[self.support_others], axis=-1)
        return jnp.where(self.support_valid, slope, 0.0)

    def jacobian(self, weights: Float[Array, " K"]) -> Float[Array, "K P"]:
        """(K, P) G = d a / d w, the slopes scattered onto their columns."""
        k, width = self.n_blendshapes, self.gram.shape[0]
        rows = jnp.arange(k)[:, None]
        zeros = jnp.zeros((k, width), weights.dtype)
        return zeros.at[rows, self.support].add(self.slopes(weights))

    def objective(
        self,
        weights: Float[Array, " K"],
        projection: Float[Array, " P"],
        offset_sq: Float[Array, ""],
        alpha: float | Float[Array, ""],
    ) -> Float[Array, ""]:
        """1/2 ||f(w) - b||^2 + alpha 1^T w from p = M^T (b - b0) and ||b - b0||^2:
        1/2 (a^T Q a - 2 a^T p + ||b - b0||^2) + alpha 1^T w, P x P work."""
        a = self.coefficients(weights)
        value = 0.5 * (a @ self.gram @ a - 2.0 * a @ projection + offset_sq) + alpha * weights.sum()
        return value if self.constant_term is None else value + self.constant_term

    def projection(self, offset: Float[Array, " N"]) -> Float[Array, " P"]:
        """p = M^T (b - b0) for ``offset`` = (b - b0).ravel(): the one 3V-sized product
        (plus ``linear_term`` when a penalty set one)."""
        projection = self.columns @ offset
        return projection if self.linear_term is None else projection + self.linear_term

    def mesh(self, weights: Float[Array, " K"]) -> Float[Array, "V 3"]:
        return self.neutral + (self.coefficients(weights) @ self.columns).reshape(-1, 3)


def prepare(
    rig: BlendshapeRig, *, drop_zero_shapes: bool = False, points: Any = None
) -> InverseProblem:
    """Precompute M and Q for ``rig`` (float64 accumulation; a few seconds for ict-quartic).

    ``points``: solve from a few points of the surface instead of the whole mesh (markers,
    tracked landmarks): (N,) vertex indices, (triangles (N,), barycentric (N, 3)) on
    ``rig.faces``, or a ``mesh.SurfaceMap`` onto the rig's mesh (``mesh.bind_points`` binds a
    landmark layout to a head). The problem is then that of the rig at the points
    (``problem.rig``: N vertices, no faces) and targets are (N, 3) point positions; a
    blendshape that moves none of the points is kept with a warning (its weight is then
    fixed by the L1 term and the start alone). Points outside the mesh raise a ValueError
    naming ``points``.

    A blendshape with all-zero deltas cannot be solved for (its weight is undetermined):
    ``prepare`` raises a ValueError naming it, or, with ``drop_zero_shapes=True``, warns and
    prepares the rig without it (and without the correctives that involve it); the problem's
    ``rig`` is then that smaller rig, whose ``names`` the solved weights follow.
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    k = rig.n_blendshapes
    if k == 0:
        raise ValueError("rig: has no blendshapes (K = 0); there are no weights to solve for")
    if points is not None:
        rig = points_rig(rig, points)
    norms = np.linalg.norm(np.asarray(rig.deltas, np.float64).reshape(k, -1), axis=1)
    if np.any(norms == 0):
        zero = np.flatnonzero(norms == 0).tolist()
        names = [rig.names[i] for i in zero] if rig.names else zero
        if points is not None and not drop_zero_shapes:
            warn(f"prepare: blendshapes {names} move none of the points")
        elif not drop_zero_shapes:
            raise ValueError(
                f"rig: blendshapes {names} have all-zero deltas (zero norm), so their weights "
                "are undetermined; pass drop_zero_shapes=True to prepare the rig without them"
            )
        if len(zero) == k:
            raise ValueError("rig: every blendshape has all-zero deltas; nothing to solve for")
        if drop_zero_shapes:
            warn(
                f"prepare: dropping blendshapes {names} (all-zero deltas); solved weights "
                "follow problem.rig.names",
            )
            rig = _without_shapes(rig, zero)
            k = rig.n_blendshapes
    v = rig.n_vertices
    columns = [np.asarray(rig.deltas, np.float64).reshape(k, -1)]
    tables = sorted((c for c in rig.correctives if c.indices.shape[0]), key=lambda c: c.order)
    for table in tables:
        columns.append(table.to_dense(v).reshape(table.indices.shape[0], -1).astype(np.float64))
    rows = np.concatenate(columns)  # (P, 3V)
    norms = np.linalg.norm(rows[:k], axis=1)
    gram = rows @ rows.T
    support, others, valid = _coordinate_supports(k, [np.asarray(t.indices) for t in tables])
    support_gram = np.where(valid[..., None], gram[support], 0.0)
    block = np.take_along_axis(support_gram, support[:, None, :], axis=2)
    support_block = np.where(valid[:, :, None] & valid[:, None, :], block, 0.0)
    return InverseProblem(
        neutral=jnp.asarray(rig.neutral),
        columns=jnp.asarray(rows, jnp.float32),
        gram=jnp.asarray(gram, jnp.float32),
        combinations=tuple(jnp.asarray(t.indices) for t in tables),
        blendshape_norms=jnp.asarray(norms, jnp.float32),
        pseudoinverse=jnp.asarray(np.linalg.pinv(rows[:k].T), jnp.float32),
        pair_hessian_bounds=jnp.asarray(_pair_hessian_bounds(rig, k), jnp.float32),
        support=jnp.asarray(support),
        support_others=jnp.asarray(others),
        support_valid=jnp.asarray(valid),
        support_gram=jnp.asarray(support_gram, jnp.float32),
        support_block=jnp.asarray(support_block, jnp.float32),
        rig=rig,
    )


def _without_shapes(rig: BlendshapeRig, drop: list[int]) -> BlendshapeRig:
    """``rig`` without blendshapes ``drop`` and without the correctives that involve them."""
    k = rig.n_blendshapes
    keep = np.setdiff1d(np.arange(k), drop)
    new_index = np.full(k, -1, np.int64)
    new_index[keep] = np.arange(len(keep))
    tables = []
    for table in rig.correctives:
        indices = np.asarray(table.indices)
        rows = np.flatnonzero(np.all(new_index[indices] >= 0, axis=1))
        if rows.size:
            deltas = np.asarray(table.deltas)[rows]
            tables.append(Corrective(new_index[indices[rows]], table.vertices, deltas))
    names = tuple(rig.names[i] for i in keep) if rig.names else ()
    return BlendshapeRig(
        rig.neutral, rig.deltas[keep], tuple(tables), names, rig.faces, units=rig.units
    )


def _coordinate_supports(
    k: int, tables: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every weight i, the columns of M whose coefficient depends on w_i (column i and the
    combinations containing i, in column order) and the other weights of each; padded to the
    largest count m. The coefficient of such a column is w_i times the product of the others,
    so d a / d w_i is that product on these columns and zero elsewhere."""
    n_others = max([t.shape[1] - 1 for t in tables] + [1])
    entries: list[list[tuple[int, list[int]]]] = [[(i, [])] for i in range(k)]
    column = k
    for table in tables:
        for row in table.tolist():
            for i in row:
                entries[i].append((column, [j for j in row if j != i]))
            column += 1
    m = max(len(e) for e in entries)
    support = np.repeat(np.arange(k, dtype=np.int32)[:, None], m, axis=1)
    others = np.full((k, m, n_others), k, np.int32)
    valid = np.zeros((k, m), bool)
    for i, rows in enumerate(entries):
        for slot, (col, rest) in enumerate(rows):
            support[i, slot], valid[i, slot] = col, True
            others[i, slot, : len(rest)] = rest
    return support, others, valid


def _pair_hessian_bounds(rig: BlendshapeRig, k: int, chunk: int = 2048) -> np.ndarray:
    pairs = rig.corrective(2)
    n = 3 * rig.n_vertices
    if pairs is None or pairs.indices.shape[0] == 0:
        return np.zeros((n, 3))
    rows, cols = np.asarray(pairs.indices).T
    dense = pairs.to_dense(rig.n_vertices).reshape(len(rows), -1).astype(np.float64)
    bounds = np.empty((n, 3))
    for start in range(0, n, chunk):
        block = dense[:, start : start + chunk].T  # (chunk, C2)
        hessian = np.zeros((block.shape[0], k, k))
        hessian[:, rows, cols] = block / 2
        hessian[:, cols, rows] = block / 2
        eig = np.linalg.eigvalsh(hessian)
        bounds[start : start + chunk] = np.stack(
            [eig[:, 0], eig[:, -1], np.abs(eig).max(axis=1)], axis=1
        )
    return bounds
