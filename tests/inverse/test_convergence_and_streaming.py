"""The stopping rule, the active-set Newton step, one-frame streaming and compile-once takes,
on the real ict-quartic rig driven by real Live Link Face frames (+ the paper's noise)."""

from __future__ import annotations

import logging

import jax
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.inverse import CARDINALITY_TOL
from canrig_jax.inverse._coordinate_descent import objective
from canrig_jax.rig import evaluate


@pytest.fixture(scope="module")
def noisy(ict_quartic, livelink_weights):
    weights = livelink_weights[[10, 70, 120, 170]]
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(ict_quartic, weights))
    noise = np.random.default_rng(3).normal(0, np.sqrt(0.03), clean.shape)
    return (clean + noise).astype(np.float32)


def _cardinality(weights):
    return (np.asarray(weights) > CARDINALITY_TOL).sum(1)


@pytest.mark.slow
def test_stopping_rule_and_newton_step_reach_the_minimum_of_plain_cd_in_fewer_passes(
    ict_quartic_problem, noisy
):
    problem, alpha = ict_quartic_problem, 5.0
    # the minimum: Algorithm 1 run for 150 passes (no stopping rule, no Newton step)
    plain = inverse.QuarticCD(alpha=alpha, passes=150, tol=0.0, newton=False)
    reference = inverse.solve_sequence(problem, noisy, plain)
    fast = inverse.solve_sequence(problem, noisy, inverse.QuarticCD(alpha=alpha))
    objective, minimum = np.asarray(fast.objective), np.asarray(reference.objective)
    assert np.all(objective <= minimum * (1 + 3e-5)), (objective - minimum) / minimum
    steps = np.asarray(fast.stats["steps"])
    assert np.all(np.asarray(fast.stats["converged"])) and steps.max() < 40, steps
    # the Newton step keeps coordinate descent's sparsity
    assert np.all(_cardinality(fast.weights) <= _cardinality(reference.weights) + 1)
    # and the history is the objective after each pass, never increasing
    history = np.asarray(fast.history)
    assert np.all(np.diff(history, axis=1) <= 1e-6 * np.abs(history[:, 1:]))


def _count_compiles(caplog, name):
    return sum(f"Compiling jit({name})" in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_solve_sequence_and_stream_compile_once(ict_quartic_problem, noisy, caplog):
    problem = ict_quartic_problem
    caplog.set_level(logging.WARNING, logger="jax")
    with jax.log_compiles():
        for alpha, frames in ((0.5, noisy[:2]), (2.0, noisy[2:]), (0.5, noisy[1:3])):
            method = inverse.QuarticCD(alpha=alpha, passes=3)
            inverse.solve_sequence(problem, frames, method).weights.block_until_ready()
        assert _count_compiles(caplog, "_solve_batch") == 1
        stream = inverse.Stream(problem, inverse.QuarticCD(alpha=0.5, passes=3), warm_start=True)
        for frame in noisy:
            stream(frame).weights.block_until_ready()
        inverse.solve(problem, noisy[0], inverse.QuarticCD(alpha=1.0, passes=3))
        assert _count_compiles(caplog, "_solve_one") == 1


@pytest.mark.slow
def test_stream_with_warm_starts_equals_the_warm_started_take(ict_quartic_problem, noisy):
    method = inverse.QuarticCD(alpha=0.5, passes=4)
    take = inverse.solve_sequence(ict_quartic_problem, noisy, method, warm_start=True)
    stream = inverse.Stream(ict_quartic_problem, method, warm_start=True)
    for frame, target in enumerate(noisy):
        weights = np.asarray(stream(target).weights)
        np.testing.assert_allclose(weights, np.asarray(take.weights[frame]), atol=2e-3)


def test_random_order_draws_a_permutation_per_frame(ict_quartic_problem, noisy):
    same = np.stack([noisy[0], noisy[0]])
    method = inverse.QuarticCD(alpha=0.5, passes=1, tol=0.0, newton=False, order="random")
    first = np.asarray(inverse.solve_sequence(ict_quartic_problem, same, method).weights)
    assert np.abs(first[0] - first[1]).max() > 1e-3  # two frames, two orders
    again = np.asarray(inverse.solve_sequence(ict_quartic_problem, same, method).weights)
    np.testing.assert_array_equal(first, again)  # reproducible from the key


@pytest.mark.slow
def test_lmmm_on_a_rig_without_correctives_reaches_the_convex_minimum(ict_face, livelink_weights):
    """With no pair correctives LMMM's majoriser is quadratic; on the linear rig the objective
    is convex, so LMMM and converged coordinate descent approach the same minimum (LMMM used
    to return NaN for every frame of such a rig)."""
    rig = ict_face
    problem = inverse.prepare(rig)
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(rig, livelink_weights[[30, 100]]))
    targets = clean + np.random.default_rng(4).normal(0, np.sqrt(0.03), clean.shape)
    lmmm = inverse.solve_sequence(problem, targets, inverse.LMMM(alpha=0.5, iterations=400))
    cd = inverse.solve_sequence(problem, targets, inverse.LinearCD(alpha=0.5, passes=300, tol=1e-7))
    assert np.all(np.isfinite(np.asarray(lmmm.weights)))
    lmmm_value, minimum = np.asarray(lmmm.objective), np.asarray(cd.objective)
    # MM with a spectral-norm majoriser is a first-order method: close, from above
    assert np.all(lmmm_value >= minimum * (1 - 1e-5)) and np.all(lmmm_value <= minimum * (1 + 1e-3))


@pytest.mark.slow
def test_converged_quartic_cd_reaches_an_independent_float64_lbfgsb_minimum(
    ict_quartic_problem, noisy
):
    """SciPy's float64 L-BFGS-B from zero on the same objective (``reference.minimum``,
    gradient written out independently) finds no lower value than converged QuarticCD."""
    from canrig_jax.papers.inverse_rig import minimum

    problem, alpha = ict_quartic_problem, 5.0
    for target in noisy[:2]:
        cd = inverse.solve(problem, target, inverse.QuarticCD(alpha=alpha))
        best = minimum(problem, target, alpha)
        offset = (np.asarray(target) - np.asarray(problem.neutral)).ravel()
        value = float(objective(problem, best.astype(np.float32), offset, alpha))
        assert float(cd.objective) <= value * (1 + 2e-5), (float(cd.objective), value)


@pytest.mark.slow
def test_projected_newton_reaches_converged_cd_with_its_zeros(ict_quartic_problem, noisy):
    """QuarticNewton minimises the same objective: no higher than converged QuarticCD (which
    reaches the independent float64 L-BFGS-B minimum, tested above) in a handful of
    iterations, with weights exactly 0 where the L1 term holds them (cardinality within one
    of CD's), a history that never increases, and the same solution warm-started."""
    problem, alpha = ict_quartic_problem, 5.0
    cd = inverse.solve_sequence(problem, noisy, inverse.QuarticCD(alpha=alpha))
    newton = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=alpha))
    objective, reference = np.asarray(newton.objective), np.asarray(cd.objective)
    assert np.all(objective <= reference * (1 + 3e-5)), (objective - reference) / reference
    assert np.all(np.asarray(newton.stats["converged"]))
    assert np.all(np.asarray(newton.stats["steps"]) <= 15)  # a handful of joint steps
    weights = np.asarray(newton.weights)
    assert np.sum(weights == 0.0) > 0.3 * weights.size  # exact zeros, not small values
    assert np.all(np.abs(_cardinality(newton.weights) - _cardinality(cd.weights)) <= 1)
    history = np.asarray(newton.history)
    assert np.all(np.diff(history, axis=1) <= 0)
    warm = inverse.solve_sequence(
        problem, noisy, inverse.QuarticNewton(alpha=alpha), warm_start=True
    )
    np.testing.assert_allclose(np.asarray(warm.objective), objective, rtol=5e-5)


@pytest.mark.slow
def test_one_frame_branches_and_batched_branches_reach_the_same_minimum(ict_quartic_problem, noisy):
    """One frame skips the updates that change nothing, the Newton rows of fixed weights and
    the second Newton trial when no weight reaches a bound; under vmap every frame takes the
    branch the whole batch needs (``_one_frame_or_batch``). Both are the same algorithm."""
    from canrig_jax.inverse._coordinate_descent import _one_frame_or_batch

    assert int(_one_frame_or_batch(jax.numpy.asarray(3), jax.numpy.asarray(7))) == 3
    batched = jax.vmap(lambda x: _one_frame_or_batch(x, jax.numpy.asarray(7)))(np.arange(3))
    np.testing.assert_array_equal(np.asarray(batched), [7, 7, 7])

    method = inverse.QuarticCD(alpha=0.5)
    take = inverse.solve_sequence(ict_quartic_problem, noisy, method)
    stream = inverse.Stream(ict_quartic_problem, method)
    for frame, target in enumerate(noisy):
        single = stream(target)
        np.testing.assert_allclose(float(single.objective), float(take.objective[frame]), rtol=2e-5)
        np.testing.assert_allclose(
            np.asarray(single.weights), np.asarray(take.weights[frame]), atol=5e-3
        )
