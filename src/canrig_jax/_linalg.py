"""Dense linear algebra that cannot deadlock XLA's CPU thread pool: LAPACK one matrix at a time.

jaxlib 0.10's CPU LAPACK kernels (Cholesky, triangular solves, eigh, LU) split a *batch* of
matrices across XLA's intra-op thread pool and block until the pieces are done. When XLA runs
as many such calls at once as the pool has threads (two on a 2-core machine, e.g. two
independent batched triangular solves in one program), every pool thread waits for work that
only another, equally blocked, thread could run, and the call never returns: the fitted pose
A-to-B on a ``LocalFitRig`` hung on its second call. A call on *one* matrix (no batch
dimensions) runs inline on the calling thread and never waits (jaxlib's ``ParallelBatchMap``
runs a batch no larger than its chunk in place), so this module gives every LAPACK call exactly
one matrix:

- ``jax.custom_batching.sequential_vmap``: under ``vmap`` (ours or a caller's, nested or not)
  the matrices are visited by a ``lax.map`` loop, one LAPACK call each;
- ``lax.custom_linear_solve`` makes the triangular solves linear operators JAX can transpose
  (``grad``, ``linear_transpose``, ``lineax``'s LSMR), whose derivative in the matrix is exact;
- ``cholesky`` has the analytic derivative dL = L Phi(L^-1 dA L^-T) (Murray 2016) in terms of
  those solves.

The batched kernels were faster only where one program held many matrices of one size; a
benchmark (``benchmarks/bench_linalg.py``) prints the ratio. ``tests/test_linalg.py`` checks
that no compiled solve of the library keeps a batched LAPACK call, and the stress test runs the
fits that hung. Conventions follow ``jnp.linalg``: a matrix that is not positive definite gives
a NaN factor, which the callers test with ``jnp.isfinite``.
"""

from __future__ import annotations

import os
import re

import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_batching import sequential_vmap
from jaxtyping import Array, Float

BATCHED_REFERENCE = os.environ.get("CANRIG_BENCH_BATCHED_LAPACK") == "1"
"""For ``benchmarks/bench_linalg.py`` only: ``CANRIG_BENCH_BATCHED_LAPACK=1`` (read at import)
restores the previous lowering, ``jnp.linalg`` with whole batches per LAPACK call, to time
against. It can deadlock; never set it otherwise."""


@sequential_vmap
def _potrf(matrix):
    return lax.linalg.cholesky(matrix, symmetrize_input=False)


@sequential_vmap
def _forward(lower, rhs):
    return lax.linalg.triangular_solve(lower, rhs, left_side=True, lower=True)


@sequential_vmap
def _backward(lower, rhs):
    return lax.linalg.triangular_solve(lower, rhs, left_side=True, lower=True, transpose_a=True)


def _solve_lower(lower, rhs, transpose: bool):
    """L x = b (or L^T x = b), b (n, m), as a transposable linear solve."""
    solve, transpose_solve = (_backward, _forward) if transpose else (_forward, _backward)
    return lax.custom_linear_solve(
        lambda x: (lower.T if transpose else lower) @ x,
        rhs,
        lambda _, b: solve(lower, b),
        lambda _, b: transpose_solve(lower, b),
    )


def _columns(rhs, vector):
    return rhs[..., None] if vector else rhs


def solve_triangular(
    lower: Float[Array, "*batch n n"],
    rhs: Float[Array, "*batch n"] | Float[Array, "*batch n m"],
    *,
    transpose: bool = False,
    vector: bool | None = None,
) -> Array:
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
        x = _solve_lower(lower, _columns(rhs, vector), transpose)
        return x[:, 0] if vector else x

    return jnp.vectorize(one, signature=signature)(lower, rhs)


def cho_solve(
    lower: Float[Array, "*batch n n"],
    rhs: Float[Array, "*batch n"] | Float[Array, "*batch n m"],
    *,
    vector: bool | None = None,
) -> Array:
    """x with ``L L^T x = b``, L a lower Cholesky factor (``cholesky``); shapes as
    ``solve_triangular``."""
    lower, rhs = jnp.asarray(lower), jnp.asarray(rhs)
    if vector is None:
        vector = rhs.ndim == lower.ndim - 1
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


def cholesky(matrix: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
    """Lower Cholesky factor L (L L^T = A) of symmetric positive definite matrices (only
    A's lower triangle is read); NaN for a matrix that is not positive definite."""
    if BATCHED_REFERENCE:
        return jnp.linalg.cholesky(matrix)
    return jnp.vectorize(_cholesky, signature="(n,n)->(n,n)")(jnp.asarray(matrix))


def spd_solve(
    matrix: Float[Array, "*batch n n"],
    rhs: Float[Array, "*batch n"] | Float[Array, "*batch n m"],
    *,
    vector: bool | None = None,
) -> Array:
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


def eigvalsh(matrix: Float[Array, "*batch n n"]) -> Float[Array, "*batch n"]:
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


def inv(matrix: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
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
