"""Dense linear algebra that cannot deadlock XLA's CPU thread pool: LAPACK one matrix per call.

jaxlib 0.10's CPU LAPACK kernels (Cholesky, triangular solves, eigh, LU) split a *batch* of
matrices across XLA's intra-op thread pool and block until the pieces are done. When XLA runs
as many such calls at once as the pool has threads (two on a 2-core machine, e.g. two
independent batched triangular solves in one program), every pool thread waits for work that
only another, equally blocked, thread could run, and the call never returns: the fitted pose
A-to-B on a ``LocalFitRig`` hung on its second call. A call on *one* matrix never waits
(jaxlib's ``ParallelBatchMap`` runs a batch no larger than its chunk in place, on the calling
thread), so no LAPACK call made here holds more than one matrix. Under ``vmap`` (ours or a
caller's, nested or not; ``jax.custom_batching``):

- one matrix, many right-hand sides: a single call, the batch as extra columns;
- many small matrices (order <= ``SMALL``): Cholesky-Crout and substitution unrolled in
  elementwise ``jnp`` operations over the whole batch (no LAPACK at all);
- many larger matrices: one LAPACK call each, in a ``lax.map`` loop (``sequential_vmap`` for
  ``inv`` and ``eigh``).

``lax.custom_linear_solve`` keeps the triangular solves transposable (reverse mode, lineax's
LSMR), and ``cholesky``, ``inv`` and ``eigvalsh`` carry their analytic derivatives (Murray
2016 for the Cholesky factor). ``benchmarks/bench_linalg.py`` times the fits against the batched
calls; ``tests/test_linalg.py`` and ``tests/test_deadlock.py`` check that no compiled solve of
the library keeps a batched LAPACK call. Conventions follow ``jnp.linalg``: a matrix that is
not positive definite gives a NaN factor, which the callers test with ``jnp.isfinite``.
"""

import os
import re

import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_batching import custom_vmap, sequential_vmap
from jaxtyping import Array, ArrayLike, Float

BATCHED_REFERENCE = os.environ.get("CANRIG_BENCH_BATCHED_LAPACK") == "1"
"""For ``benchmarks/bench_linalg.py`` only: ``CANRIG_BENCH_BATCHED_LAPACK=1`` (read at import)
restores the previous lowering, ``jnp.linalg`` with whole batches per LAPACK call, to time
against. It can deadlock; never set it otherwise."""


SMALL = 32
"""A batch of matrices of at most this order is factorised and solved in unrolled elementwise
operations over the whole batch (their size grows with the cube of the order); larger ones take
one LAPACK call each in a loop over the batch, whose per-iteration cost would dominate for
small matrices (CANRig-PBS's local prior factorises 200 of order 17 per edit)."""


def _cholesky_columns(matrix):
    """Cholesky-Crout of one small matrix, unrolled entry by entry (elementwise operations that
    XLA fuses across a batch): L_jj = sqrt(a_jj - sum_k L_jk^2), then
    L_ij = (a_ij - sum_k L_ik L_jk) / L_jj below it, k < j."""
    n, zero = matrix.shape[0], jnp.zeros((), matrix.dtype)
    entry = {}
    for j in range(n):
        entry[j, j] = jnp.sqrt(matrix[j, j] - sum((entry[j, k] ** 2 for k in range(j)), zero))
        for i in range(j + 1, n):
            coupling = sum((entry[i, k] * entry[j, k] for k in range(j)), zero)
            entry[i, j] = (matrix[i, j] - coupling) / entry[j, j]
    lower = jnp.stack([jnp.stack([entry.get((i, j), zero) for j in range(n)]) for i in range(n)])
    return jnp.where(jnp.all(jnp.isfinite(lower)), lower, jnp.nan)  # as LAPACK's: all NaN


def _substitution(lower, rhs, transpose):
    """L x = b (L^T x = b with ``transpose``) of one small matrix, unrolled over its rows."""
    n = lower.shape[0]
    matrix = lower.T if transpose else lower
    order = range(n - 1, -1, -1) if transpose else range(n)
    rows = {}
    for i in order:
        coupling = sum((matrix[i, k] * rows[k] for k in rows), jnp.zeros_like(rhs[i]))
        rows[i] = (rhs[i] - coupling) / matrix[i, i]
    return jnp.stack([rows[i] for i in range(n)])


def _one_matrix_per_call(lapack, small):
    """``lapack`` (one matrix, then right-hand sides) under ``vmap``: where only the
    right-hand sides are batched, one call with the batch as extra columns; else ``small``
    over the whole batch where the matrices have order <= ``SMALL``, or one ``lapack`` call
    per matrix in a loop."""
    fn = custom_vmap(lapack)

    @fn.def_vmap
    def rule(axis_size, in_batched, matrix, *rhs):
        if rhs and not in_batched[0]:  # (B, n, m) right-hand sides: (n, B m) columns
            (rhs,) = rhs
            columns = jnp.moveaxis(rhs, 0, 1).reshape(rhs.shape[1], -1)
            x = fn(matrix, columns).reshape(rhs.shape[1], axis_size, rhs.shape[2])
            return jnp.moveaxis(x, 1, 0), True
        if matrix.shape[-1] <= SMALL:
            axes = [0 if batched else None for batched in in_batched]
            return jax.vmap(small, in_axes=axes)(matrix, *rhs), True
        args = [
            arg if batched else jnp.broadcast_to(arg, (axis_size, *arg.shape))
            for arg, batched in zip((matrix, *rhs), in_batched, strict=True)
        ]
        return lax.map(lambda one: fn(*one), tuple(args)), True

    return fn


_potrf = _one_matrix_per_call(
    lambda matrix: lax.linalg.cholesky(matrix, symmetrize_input=False), _cholesky_columns
)
_forward = _one_matrix_per_call(
    lambda lower, rhs: lax.linalg.triangular_solve(lower, rhs, left_side=True, lower=True),
    lambda lower, rhs: _substitution(lower, rhs, False),
)
_backward = _one_matrix_per_call(
    lambda lower, rhs: lax.linalg.triangular_solve(
        lower, rhs, left_side=True, lower=True, transpose_a=True
    ),
    lambda lower, rhs: _substitution(lower, rhs, True),
)


def _solve_lower(lower, rhs, transpose: bool):
    """L x = b (or L^T x = b), b (n, m), as a transposable linear solve."""
    solve, transpose_solve = (_backward, _forward) if transpose else (_forward, _backward)
    return lax.custom_linear_solve(
        lambda x: (lower.T if transpose else lower) @ x,
        rhs,
        lambda _, b: solve(lower, b),
        lambda _, b: transpose_solve(lower, b),
    )


def solve_triangular(
    lower: Float[ArrayLike, "*#batch n n"],
    rhs: Float[ArrayLike, "*#batch n"] | Float[ArrayLike, "*#batch n m"],
    *,
    transpose: bool = False,
    vector: bool | None = None,
) -> Float[Array, "*#batch n"] | Float[Array, "*#batch n m"]:
    """x with ``L x = b`` (``L^T x = b`` with ``transpose``), L lower triangular (its upper
    triangle must be zero). ``rhs`` is (..., n) when ``vector`` (default: when it has one
    dimension fewer than ``lower``), else (..., n, m); leading dimensions broadcast."""
    lower, rhs = jnp.asarray(lower), jnp.asarray(rhs)
    if vector is None:
        vector = rhs.ndim == lower.ndim - 1
    signature = "(n,n),(n)->(n)" if vector else "(n,n),(n,m)->(n,m)"

    def one(lower, rhs):
        if BATCHED_REFERENCE:
            return jax.scipy.linalg.solve_triangular(lower, rhs, lower=True, trans=int(transpose))
        if vector:
            return _solve_lower(lower, rhs[:, None], transpose)[:, 0]
        return _solve_lower(lower, rhs, transpose)

    return jnp.vectorize(one, signature=signature)(lower, rhs)


def cho_solve(
    lower: Float[ArrayLike, "*#batch n n"],
    rhs: Float[ArrayLike, "*#batch n"] | Float[ArrayLike, "*#batch n m"],
    *,
    vector: bool | None = None,
) -> Float[Array, "*#batch n"] | Float[Array, "*#batch n m"]:
    """x with ``L L^T x = b``, L a lower Cholesky factor (``cholesky``); shapes as
    ``solve_triangular``."""
    forward = solve_triangular(lower, rhs, vector=vector)
    return solve_triangular(lower, forward, transpose=True, vector=vector)


@jax.custom_jvp
def _cholesky(matrix):
    return _potrf(matrix)


@_cholesky.defjvp
def _cholesky_jvp(primals, tangents):
    # dL = L Phi(L^-1 dA L^-T), Phi: the lower triangle with half the diagonal
    (matrix,), (tangent,) = primals, tangents
    lower = _cholesky(matrix)
    tangent = 0.5 * (tangent + tangent.T)
    left = _solve_lower(lower, tangent, False)  # L^-1 dA
    middle = _solve_lower(lower, left.T, False)  # L^-1 dA L^-T (dA symmetric)
    phi = jnp.tril(middle) - 0.5 * jnp.diag(jnp.diagonal(middle))
    return lower, lower @ phi


def cholesky(matrix: Float[ArrayLike, "*batch n n"]) -> Float[Array, "*batch n n"]:
    """Lower Cholesky factor L (L L^T = A) of symmetric positive definite matrices (only
    A's lower triangle is read); NaN for a matrix that is not positive definite."""
    if BATCHED_REFERENCE:
        return jnp.linalg.cholesky(matrix)
    return jnp.vectorize(_cholesky, signature="(n,n)->(n,n)")(jnp.asarray(matrix))


def spd_solve(
    matrix: Float[ArrayLike, "*#batch n n"],
    rhs: Float[ArrayLike, "*#batch n"] | Float[ArrayLike, "*#batch n m"],
    *,
    vector: bool | None = None,
) -> Float[Array, "*#batch n"] | Float[Array, "*#batch n m"]:
    """x with ``A x = b`` for symmetric positive definite A, by ``cholesky`` and
    ``cho_solve`` (NaN where A is not positive definite)."""
    return cho_solve(cholesky(matrix), rhs, vector=vector)


@sequential_vmap
def _eigh(matrix):
    return jnp.linalg.eigh(matrix)


@jax.custom_jvp
def _eigvalsh(matrix):
    return _eigh(matrix)[0]


@_eigvalsh.defjvp
def _eigvalsh_jvp(primals, tangents):
    # d lambda_i = v_i^T dA v_i (distinct eigenvalues)
    (matrix,), (tangent,) = primals, tangents
    values, vectors = _eigh(matrix)
    return values, jnp.einsum("ji,jk,ki->i", vectors, 0.5 * (tangent + tangent.T), vectors)


def eigvalsh(matrix: Float[ArrayLike, "*batch n n"]) -> Float[Array, "*batch n"]:
    """Eigenvalues of symmetric matrices in ascending order (derivative valid where they are
    distinct)."""
    if BATCHED_REFERENCE:
        return jnp.linalg.eigvalsh(matrix)
    return jnp.vectorize(_eigvalsh, signature="(n,n)->(n)")(jnp.asarray(matrix))


@sequential_vmap
def _lu_inverse(matrix):
    return jnp.linalg.inv(matrix)


@jax.custom_jvp
def _inv(matrix):
    return _lu_inverse(matrix)


@_inv.defjvp
def _inv_jvp(primals, tangents):
    # d(A^-1) = -A^-1 dA A^-1
    (matrix,), (tangent,) = primals, tangents
    inverse = _inv(matrix)
    return inverse, -inverse @ tangent @ inverse


def inv(matrix: Float[ArrayLike, "*batch n n"]) -> Float[Array, "*batch n n"]:
    """Inverses of square matrices by LU with partial pivoting (for systems that rounding
    may leave indefinite, where ``cholesky`` would give NaN); jit/vmap/grad-safe."""
    if BATCHED_REFERENCE:
        return jnp.linalg.inv(matrix)
    return jnp.vectorize(_inv, signature="(n,n)->(n,n)")(jnp.asarray(matrix))


_LAPACK_CALL = re.compile(
    r'custom_call_target="(lapack_\w+)", operand_layout_constraints=\{\w+\[([0-9,]*)\]'
)


def lapack_calls(hlo_text: str) -> list[tuple[str, tuple[int, ...]]]:
    """(kernel, shape of its first operand) of every LAPACK custom call in a compiled
    program's HLO text (``jax.jit(f).lower(...).compile().as_text()``, or XLA's dumps). A
    shape of more than two dimensions is a batched call, the kind that can deadlock."""
    return [
        (name, tuple(int(d) for d in dims.split(",") if d))
        for name, dims in _LAPACK_CALL.findall(hlo_text)
    ]
