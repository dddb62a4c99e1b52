"""``canrig_jax._linalg``: values against float64 NumPy, derivatives against ``jnp.linalg``'s
(symmetrised: ours read one triangle of a symmetric matrix), NaN for a matrix that is not
positive definite, and the property that keeps XLA's CPU pool from deadlocking: however the
functions are batched (``vmap``, nested, under ``grad``), every LAPACK call in the compiled
program holds one matrix. Small random matrices: this is algebra, not a rig."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import _linalg as la


def _spd(rng, *shape):
    m = rng.standard_normal(shape)
    return (m @ np.swapaxes(m, -1, -2) + shape[-1] * np.eye(shape[-1])).astype(np.float32)


@jax.jit
def _every_function(a, b, lower, general):
    """Every function of the module at once: one compiled program per shape (called op by op,
    each of the unrolled small-matrix operations would compile on its own)."""
    return {
        "cholesky": la.cholesky(a),
        "spd_solve": la.spd_solve(a, b),
        "cho_solve": la.cho_solve(lower, b),
        "forward": la.solve_triangular(lower, b),
        "backward": la.solve_triangular(lower, b[..., None], transpose=True),
        "eigvalsh": la.eigvalsh(a),
        "inv": la.inv(general),
    }


@pytest.mark.parametrize("n", [1, 7, 59])
def test_values_match_float64_numpy(n):
    rng = np.random.default_rng(n)
    a, b = _spd(rng, 3, n, n), rng.standard_normal((3, n)).astype(np.float32)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    lower = np.linalg.cholesky(a64)
    general = a + rng.standard_normal(a.shape).astype(np.float32)  # not symmetric
    got = _every_function(a, b, lower.astype(np.float32), general)
    scale = np.abs(lower).max()
    np.testing.assert_allclose(got["cholesky"], lower, atol=1e-5 * scale)
    x = np.linalg.solve(a64, b64[..., None])[..., 0]
    np.testing.assert_allclose(got["spd_solve"], x, atol=1e-5 * np.abs(x).max())
    np.testing.assert_allclose(got["cho_solve"], x, atol=1e-5 * np.abs(x).max())
    y = np.linalg.solve(lower, b64[..., None])[..., 0]
    np.testing.assert_allclose(got["forward"], y, atol=1e-5 * np.abs(y).max())
    z = np.linalg.solve(np.swapaxes(lower, -1, -2), b64[..., None])  # matrix right-hand side
    np.testing.assert_allclose(got["backward"], z, atol=1e-5 * np.abs(z).max())
    eig = np.linalg.eigvalsh(a64)
    np.testing.assert_allclose(got["eigvalsh"], eig, atol=1e-5 * np.abs(eig).max())
    inverse = np.linalg.inv(general.astype(np.float64))
    np.testing.assert_allclose(got["inv"], inverse, atol=1e-4 * np.abs(inverse).max())


def test_not_positive_definite_gives_nan():
    rng = np.random.default_rng(0)
    a = _spd(rng, 2, 5, 5)
    a[1, 2, 2] = -100.0  # the second matrix is indefinite, the first is not
    lower, solved = jax.jit(lambda a: (la.cholesky(a), la.spd_solve(a, jnp.ones((2, 5)))))(a)
    lower = np.asarray(lower)
    assert np.isfinite(lower[0]).all()
    assert not np.isfinite(lower[1]).all()
    assert not np.isfinite(np.asarray(solved)[1]).all()


@pytest.mark.slow
def test_derivatives_match_jax_linalg():
    rng = np.random.default_rng(1)
    a, b = _spd(rng, 6, 6), rng.standard_normal(6).astype(np.float32)

    def symmetric(g):
        return 0.5 * (g + g.T)

    for ours, theirs in (
        (la.cholesky, jnp.linalg.cholesky),
        (lambda a: la.spd_solve(a, b), lambda a: jnp.linalg.solve(a, b)),
        (la.inv, jnp.linalg.inv),
        (la.eigvalsh, jnp.linalg.eigvalsh),
    ):
        got = jax.grad(lambda a, f=ours: jnp.sum(jnp.sin(f(a))))(a)
        want = jax.grad(lambda a, f=theirs: jnp.sum(jnp.sin(f(a))))(a)
        if ours is not la.inv:  # ours read one triangle of a symmetric matrix
            want = symmetric(want)
        np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())
    # in the right-hand side: forward and reverse mode, and the transpose (lineax's LSMR)
    tangent = rng.standard_normal(6).astype(np.float32)
    _, forward = jax.jvp(lambda b: la.spd_solve(a, b), (b,), (tangent,))
    np.testing.assert_allclose(forward, np.linalg.solve(a, tangent), rtol=1e-4, atol=1e-6)
    lower = np.linalg.cholesky(a.astype(np.float64)).astype(np.float32)
    (transposed,) = jax.linear_transpose(lambda b: la.solve_triangular(lower, b), b)(tangent)
    np.testing.assert_allclose(transposed, np.linalg.solve(lower.T, tangent), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("n", [pytest.param(9, marks=pytest.mark.slow), la.SMALL + 8])
def test_every_lapack_call_holds_one_matrix_however_batched(n):
    rng = np.random.default_rng(2)
    a, b = _spd(rng, 4, 3, n, n), rng.standard_normal((4, 3, n)).astype(np.float32)

    def loss(a, b):
        lower = la.cholesky(a)
        x = la.cho_solve(lower, b) + la.solve_triangular(lower, b, transpose=True)
        return jnp.sum(x**2) + jnp.sum(la.inv(a)) + jnp.sum(la.eigvalsh(a))

    program = jax.jit(jax.vmap(jax.vmap(jax.value_and_grad(loss, (0, 1))))).lower(a, b).compile()
    calls = la.lapack_calls(program.as_text())  # the program run below: compiled once
    kernels = {name for name, _ in calls}
    # small factors are batched in lax, larger ones go to LAPACK one at a time
    assert ("lapack_spotrf_ffi" in kernels) == (n > la.SMALL)
    assert {"lapack_sgetrf_ffi", "lapack_ssyevd_ffi"} <= kernels
    assert all(len(shape) == 2 for _, shape in calls), calls
    # the same program in jnp.linalg batches them: what the scan must catch
    batched = jax.jit(jax.vmap(lambda a: jnp.linalg.cholesky(a)))
    assert any(len(s) > 2 for _, s in la.lapack_calls(batched.lower(a[0]).compile().as_text()))
    values, (grad_a, grad_b) = program(a, b)
    np.testing.assert_allclose(values, jax.jit(jax.vmap(jax.vmap(loss)))(a, b), rtol=1e-5)
    one = jax.jit(jax.value_and_grad(loss, (0, 1)))(a[1, 2], b[1, 2])  # unbatched: LAPACK
    np.testing.assert_allclose(grad_a[1, 2], one[1][0], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(grad_b[1, 2], one[1][1], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("n", [9, la.SMALL + 8])
def test_one_matrix_many_right_hand_sides(n):
    """A shared matrix under ``vmap`` of the right-hand side: one call with the batch as
    columns, the same solutions as NumPy's."""
    rng = np.random.default_rng(3)
    a, b = _spd(rng, n, n), rng.standard_normal((5, 4, n)).astype(np.float32)
    lower = la.cholesky(a)
    x = jax.jit(jax.vmap(jax.vmap(lambda b: la.cho_solve(lower, b))))(b)
    want = np.linalg.solve(a.astype(np.float64), b.reshape(-1, n).T).T.reshape(b.shape)
    np.testing.assert_allclose(x, want, atol=1e-5 * np.abs(want).max())
    program = jax.jit(jax.vmap(lambda b: la.cho_solve(lower, b))).lower(b[0]).compile()
    calls = la.lapack_calls(program.as_text())
    assert len(calls) == 2 and all(len(shape) == 2 for _, shape in calls)  # forward, back
