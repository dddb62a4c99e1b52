"""One frame per call near the floor: QuarticNewton's reused Gauss-Newton matrix (``refresh``)
and the matrix a warm-started ``Stream`` carries from frame to frame reach the same minimum
as recomputing it every iteration."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from canrig_jax import inverse
from canrig_jax.papers import inverse_rig
from canrig_jax.rig import BlendshapeRig, Corrective, evaluate_batch

ALPHA = 0.05


@pytest.fixture(scope="module")
def take(synthetic_rig):
    """(problem, noisy (T, V, 3)): a smooth 12-frame take through the synthetic rig + noise."""
    t = np.linspace(0.0, 1.0, 12)[:, None]
    phases = np.linspace(0.0, np.pi, synthetic_rig.n_blendshapes)[None]
    weights = np.clip(0.5 + 0.45 * np.sin(2 * np.pi * t + phases), 0.0, 1.0)
    clean = np.asarray(evaluate_batch(synthetic_rig, weights.astype(np.float32)))
    noise = np.random.default_rng(0).normal(0.0, 0.02, clean.shape)
    return inverse.prepare(synthetic_rig), (clean + noise).astype(np.float32)


def _energies(rig, weights, targets):
    """E(w) = 1/2 ||f(w) - b||^2 + alpha 1^T w per frame, in float64 NumPy (independent of
    the float32 coefficient-space value the solver reports)."""
    dense = inverse_rig.NumpyDenseRig(rig)
    return np.array([
        0.5 * np.sum((dense(np.asarray(w, np.float64)) - np.asarray(b, np.float64).ravel()) ** 2)
        + ALPHA * np.sum(np.asarray(w, np.float64))
        for w, b in zip(weights, targets, strict=True)
    ])  # fmt: skip


def _excess(rig, weights, reference, targets):
    """Largest relative excess of ``weights``' float64 energy over ``reference``'s."""
    mine, best = _energies(rig, weights, targets), _energies(rig, reference, targets)
    return float(np.max((mine - best) / best))


def test_the_initial_matrix_is_the_gauss_newton_matrix_at_zero(take):
    problem, _ = take
    at, matrix, carried = inverse.QuarticNewton().initial_carry(problem)
    jacobian = np.asarray(problem.jacobian(jnp.zeros(problem.n_blendshapes)), np.float64)
    expected = jacobian @ np.asarray(problem.gram, np.float64) @ jacobian.T
    np.testing.assert_array_equal(np.asarray(at), 0.0)
    np.testing.assert_allclose(np.asarray(matrix), expected, rtol=1e-6)
    assert not bool(carried)


@pytest.mark.parametrize("refresh", [8])
def test_a_reused_matrix_reaches_the_same_minimum(take, refresh):
    problem, noisy = take
    fresh = inverse.QuarticNewton(alpha=ALPHA)
    reused = inverse.QuarticNewton(alpha=ALPHA, refresh=refresh)
    ones = [inverse.solve(problem, b, reused) for b in noisy]  # one frame: the lazy branch
    reference = [inverse.solve(problem, b, fresh).weights for b in noisy]
    assert all(bool(s.stats["converged"]) for s in ones)
    assert _excess(problem.rig, [s.weights for s in ones], reference, noisy) < 1e-4


@pytest.mark.parametrize("refresh", [4])
def test_a_warm_stream_with_its_carried_matrix_matches_warm_solves(take, refresh):
    """The carry changes the work, not the answer: each frame equals a fresh solve started
    from the previous frame's weights."""
    problem, noisy = take
    stream = inverse.Stream(problem, inverse.QuarticNewton(alpha=ALPHA, refresh=refresh),
                            warm_start=True)  # fmt: skip
    previous = jnp.zeros(problem.n_blendshapes)
    streamed, alone = [], []
    for b in noisy:
        solution = stream(b)
        assert bool(solution.stats["converged"])
        alone.append(inverse.solve(problem, b, inverse.QuarticNewton(alpha=ALPHA), init=previous))
        streamed.append(solution.weights)
        previous = solution.weights
    assert _excess(problem.rig, streamed, [s.weights for s in alone], noisy) < 1e-4


def test_refresh_must_be_a_positive_integer():
    with pytest.raises(ValueError, match="refresh"):
        inverse.QuarticNewton(refresh=0)


@pytest.mark.slow
def test_under_vmap_the_matrix_is_recomputed_every_iteration(take):
    """A take shares one branch: the batched solve with ``refresh`` equals the default's."""
    problem, noisy = take
    a = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=ALPHA, refresh=8))
    b = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=ALPHA))
    np.testing.assert_array_equal(np.asarray(a.weights), np.asarray(b.weights))
    assert jax.tree.structure(a) == jax.tree.structure(b)


@pytest.mark.bad_input
def test_per_weight_bounds_of_the_wrong_length_are_named_before_compiling(take):
    problem, noisy = take
    method = inverse.QuarticNewton(upper=np.ones(problem.n_blendshapes + 1))
    for call in (
        lambda: inverse.solve(problem, noisy[0], method),
        lambda: inverse.solve_sequence(problem, noisy, method),
        lambda: inverse.Stream(problem, method),
    ):
        with pytest.raises(ValueError, match=r"upper: expected \(8,\) per-weight bounds"):
            call()


@pytest.mark.slow
def test_a_stalled_line_search_is_not_reported_as_converged(synthetic_rig):
    """With one step length, an overshooting full step finds no decrease: those frames end
    ``stagnation`` (the Gauss-Newton model still predicted a decrease above ``tol``), and every
    frame reported ``successful`` is at the converged minimum (float64 energy). The
    correctives are scaled up so that the rig is far from quadratic and full steps overshoot."""
    scaled = tuple(
        Corrective(c.indices, c.vertices, np.asarray(c.deltas) * 20.0)
        for c in synthetic_rig.correctives
    )
    rig = BlendshapeRig(synthetic_rig.neutral, synthetic_rig.deltas, scaled, synthetic_rig.names)
    weights = np.random.default_rng(1).uniform(0.0, 1.0, (12, 8)).astype(np.float32)
    clean = np.asarray(evaluate_batch(rig, weights))
    noisy = (clean + np.random.default_rng(2).normal(0.0, 0.02, clean.shape)).astype(np.float32)
    problem = inverse.prepare(rig)
    short = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=ALPHA, line_steps=1))
    full = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=ALPHA))
    ok = np.asarray(short.result == optx.RESULTS.successful)
    assert not ok.all()  # some full steps overshoot on this rig
    assert np.array_equal(ok, np.asarray(short.stats["converged"]))
    excess = _energies(rig, short.weights, noisy) / _energies(rig, full.weights, noisy) - 1.0
    assert np.all(excess[ok] < 1e-4)
    assert np.all(np.asarray(short.result == optx.RESULTS.stagnation)[~ok])
