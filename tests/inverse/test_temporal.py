"""TemporalNewton (the whole-take inverse rig with a smoothness penalty) against independent
computations: a dense linear solve, the per-frame solver, the box KKT conditions of E through
``rig.evaluate`` and autodiff, and the NumPy/SciPy re-implementation of the authors' holistic
coordinate descent."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.inverse._temporal import (
    block_banded_solve,
    dense_banded_solve,
    difference_bands,
)
from canrig_jax.papers import inverse_rig
from canrig_jax.rig import evaluate

ALPHA = 0.5


@pytest.fixture(scope="module")
def take(synthetic_rig):
    """(problem, noisy targets (T, V, 3), clean weights (T, K)): smooth, sparse weight curves
    on the synthetic rig, noise of variance 0.03 cm^2."""
    rng = np.random.default_rng(5)
    frames, k = 16, synthetic_rig.n_blendshapes
    time = np.linspace(0.0, 1.0, frames)[:, None]
    phase, speed = rng.uniform(0, 1, (1, k)), rng.uniform(0.5, 1.5, (1, k))
    weights = np.clip(0.5 + 0.6 * np.sin(2 * np.pi * (speed * time + phase)), 0.0, 1.0)
    weights[weights < 0.3] = 0.0
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(synthetic_rig, weights))
    noisy = (clean + rng.normal(0, np.sqrt(0.03), clean.shape)).astype(np.float32)
    return inverse.prepare(synthetic_rig), noisy, weights


def _offsets(problem, targets):
    return (targets - np.asarray(problem.neutral)).reshape(len(targets), -1)


def _energy(rig, targets, weights, alpha, smoothness, velocity=0.0):
    """E(W) through the rig itself (float64 NumPy), independent of the Gram-matrix path."""
    weights = np.asarray(weights, np.float64)
    meshes = np.asarray(jax.vmap(evaluate, (None, 0))(rig, weights.astype(np.float32)))
    data = 0.5 * ((meshes.astype(np.float64) - targets) ** 2).sum()
    second = np.diff(weights, n=2, axis=0)
    first = np.diff(weights, axis=0)
    time = 0.5 * smoothness * (second**2).sum() + 0.5 * velocity * (first**2).sum()
    return data + alpha * weights.sum() + time


@pytest.mark.parametrize("solver", [block_banded_solve, dense_banded_solve])
@pytest.mark.parametrize("frames", [1, 2, 5, 6])
def test_block_banded_solve_equals_a_dense_solve(frames, solver):
    """Both solvers of the block-banded system (the scan over frame pairs, and the one dense
    matrix of a short window) against NumPy's solve of the matrix built here."""
    rng = np.random.default_rng(frames)
    k = 3
    dense = np.zeros((frames * k, frames * k))
    for t in range(frames):
        a = rng.normal(size=(k, k))
        dense[t * k : (t + 1) * k, t * k : (t + 1) * k] = a @ a.T + 0.5 * np.eye(k)
    second, first = difference_bands(frames, 2), difference_bands(frames, 1)
    # the bands are those of D^T D and D1^T D1
    d2, d1 = np.diff(np.eye(frames), n=2, axis=0), np.diff(np.eye(frames), axis=0)
    for bands, d in ((second, d2), (first, d1)):
        for offset in range(3):
            np.testing.assert_allclose(
                bands[offset][: max(frames - offset, 0)], np.diag(d.T @ d, offset)
            )
    dense += np.kron(3.0 * d2.T @ d2 + 0.7 * d1.T @ d1, np.eye(k))
    # arbitrary (non-diagonal) coupling blocks too
    for t in range(frames - 1):
        c = 0.2 * rng.normal(size=(k, k))
        dense[(t + 1) * k : (t + 2) * k, t * k : (t + 1) * k] += c
        dense[t * k : (t + 1) * k, (t + 1) * k : (t + 2) * k] += c.T
    dense += frames * np.eye(frames * k)  # keep it positive definite
    rhs = rng.normal(size=(frames, k))

    def band(offset):
        blocks = [
            dense[(t + offset) * k : (t + offset + 1) * k, t * k : (t + 1) * k]
            for t in range(frames - offset)
        ]
        return jnp.asarray(np.stack(blocks) if blocks else np.zeros((0, k, k)), jnp.float32)

    x = solver(band(0), band(1), band(2), jnp.asarray(rhs, jnp.float32))
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(frames, k)
    np.testing.assert_allclose(np.asarray(x), expected, atol=1e-5)


@pytest.mark.slow
def test_zero_smoothness_is_the_per_frame_solution(take):
    problem, targets, _ = take
    zero = inverse.TemporalNewton(alpha=ALPHA, smoothness=0.0, tol=1e-7)
    joint = inverse.solve_sequence(problem, targets, zero)
    frames = inverse.solve_sequence(problem, targets, inverse.QuarticNewton(alpha=ALPHA, tol=1e-7))
    np.testing.assert_allclose(np.asarray(joint.weights), np.asarray(frames.weights), atol=2e-3)
    np.testing.assert_allclose(np.asarray(joint.objective), np.asarray(frames.objective), rtol=1e-4)
    # one frame alone (solve): the time terms vanish whatever the smoothness
    one = inverse.solve(problem, targets[3], inverse.TemporalNewton(alpha=ALPHA, smoothness=50.0))
    newton = inverse.solve(problem, targets[3], inverse.QuarticNewton(alpha=ALPHA))
    np.testing.assert_allclose(np.asarray(one.weights), np.asarray(newton.weights), atol=1e-5)
    assert int(one.stats["steps"]) == int(newton.stats["steps"])


@pytest.mark.slow
def test_temporal_solution_is_a_box_kkt_point_with_lower_energy(synthetic_rig, take):
    problem, targets, _ = take
    smoothness, velocity = 20.0, 2.0
    method = inverse.TemporalNewton(
        alpha=ALPHA, smoothness=smoothness, velocity=velocity, tol=1e-8, iterations=200
    )
    solution = inverse.solve_sequence(problem, targets, method)
    weights = np.asarray(solution.weights, np.float64)
    assert np.all(weights >= 0) and np.all(weights <= 1)
    assert bool(np.all(solution.stats["converged"]))

    def energy(w):  # autodiff through evaluate, not through the Gram matrix
        meshes = jax.vmap(evaluate, (None, 0))(synthetic_rig, w)
        second, first = jnp.diff(w, n=2, axis=0), jnp.diff(w, axis=0)
        return (
            0.5 * jnp.sum((meshes - targets) ** 2)
            + ALPHA * w.sum()
            + 0.5 * smoothness * jnp.sum(second**2)
            + 0.5 * velocity * jnp.sum(first**2)
        )

    grad = np.asarray(jax.grad(energy)(jnp.asarray(weights, jnp.float32)), np.float64)
    projected = weights - np.clip(weights - grad, 0.0, 1.0)
    assert np.abs(projected).max() < 2e-3 * np.abs(grad).max(), np.abs(projected).max()

    per_frame = inverse.solve_sequence(problem, targets, inverse.QuarticNewton(alpha=ALPHA))
    e_temporal = _energy(synthetic_rig, targets, weights, ALPHA, smoothness, velocity)
    e_frames = _energy(synthetic_rig, targets, per_frame.weights, ALPHA, smoothness, velocity)
    assert e_temporal < e_frames
    assert inverse.roughness(weights) < inverse.roughness(np.asarray(per_frame.weights))
    # the per-frame objectives and the time terms in stats add up to the take's E
    total = float(
        solution.objective.sum()
        + solution.stats["smoothness_term"].sum()
        + solution.stats["velocity_term"].sum()
    )
    np.testing.assert_allclose(total, e_temporal, rtol=1e-4)


@pytest.mark.slow  # the batched windows' unrolled Cholesky takes ~40 s to compile
def test_windows_stitch_close_to_the_whole_take(synthetic_rig, take):
    problem, targets, _ = take
    whole = inverse.TemporalNewton(alpha=ALPHA, smoothness=20.0)
    windowed = inverse.TemporalNewton(alpha=ALPHA, smoothness=20.0, window=8)
    a = np.asarray(inverse.solve_sequence(problem, targets, whole).weights, np.float64)
    solution = inverse.solve_sequence(problem, targets, windowed)
    b = np.asarray(solution.weights, np.float64)
    assert solution.history.shape[0] == len(targets)
    assert np.all(b >= 0) and np.all(b <= 1)
    assert np.abs(a - b).mean() < 0.02 and np.abs(a - b).max() < 0.15, np.abs(a - b).max()
    e_whole = _energy(synthetic_rig, targets, a, ALPHA, 20.0)
    e_windows = _energy(synthetic_rig, targets, b, ALPHA, 20.0)
    assert e_whole <= e_windows < 1.01 * e_whole


@pytest.mark.slow
def test_the_authors_holistic_cd_reaches_the_same_objective(synthetic_rig, take):
    """One interval holding the whole take: the NumPy/SciPy coordinate descent minimises
    (2/n) E, so both reach the same E; the lambda mapping is checked on the formula."""
    problem, targets, _ = take
    targets = targets[:8]
    smoothness = 20.0
    n, k = 3 * synthetic_rig.n_vertices, synthetic_rig.n_blendshapes
    lambda1, lambda2 = inverse_rig.holistic_lambdas(ALPHA, smoothness, n, k)
    # the paper's J = (1/n)||F - B||^2 + (lambda1/m) 1^T C + lambda2 ||C D^T||^2 is (2/n) E
    w = np.random.default_rng(0).uniform(0, 1, (8, k))
    meshes = np.asarray(jax.vmap(evaluate, (None, 0))(synthetic_rig, w.astype(np.float32)))
    j = (
        ((meshes - targets) ** 2).sum() / n
        + lambda1 / k * w.sum()
        + lambda2 * (np.diff(w, n=2, axis=0) ** 2).sum()
    )
    np.testing.assert_allclose(0.5 * n * j, _energy(synthetic_rig, targets, w, ALPHA, smoothness))

    reference = inverse_rig.numpy_holistic_cd(
        synthetic_rig, targets, lambda1, lambda2, interval=8, passes_max=60
    )
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=smoothness, tol=1e-7)
    ours = inverse.solve_sequence(problem, targets, method).weights
    e_reference = _energy(synthetic_rig, targets, reference, ALPHA, smoothness)
    e_ours = _energy(synthetic_rig, targets, ours, ALPHA, smoothness)
    np.testing.assert_allclose(e_ours, e_reference, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(ours), reference, atol=0.02)


def test_bad_input_names_the_argument(take):
    problem, targets, _ = take
    for make, argument in [
        (lambda: inverse.TemporalNewton(smoothness=-1.0), "smoothness"),
        (lambda: inverse.TemporalNewton(smoothness=float("inf")), "smoothness"),
        (lambda: inverse.TemporalNewton(velocity=-0.5), "velocity"),
        (lambda: inverse.TemporalNewton(window=2), "window"),
        (lambda: inverse.TemporalNewton(window=True), "window"),
        (lambda: inverse.TemporalNewton(alpha=-1.0), "alpha"),
    ]:
        with pytest.raises(ValueError, match=argument):
            make()
    method = inverse.TemporalNewton(alpha=ALPHA)
    offsets = jnp.asarray(_offsets(problem, targets))
    init = jnp.zeros((len(targets), problem.n_blendshapes))
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="offsets"):
        method.sequence(problem, offsets[:, :-1], init, key)
    with pytest.raises(ValueError, match="init"):
        method.sequence(problem, offsets, init[:-1], key)
    with pytest.raises(ValueError, match="warm_start"):
        inverse.solve_sequence(problem, targets, method, warm_start=True)
    with pytest.raises(ValueError, match="targets"):
        inverse.solve_sequence(problem, targets[:, :-1], method)
    with pytest.raises(ValueError, match="interval"):
        inverse_rig.numpy_holistic_cd(problem.rig, targets, 0.1, 0.1, interval=2)
