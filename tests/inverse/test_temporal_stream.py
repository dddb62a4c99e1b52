"""The lagged temporal ``Stream`` and the temporal default against independent computations:
a SciPy solve of each window's objective with the earlier frames fixed, the batch temporal
solve, the plain warm-started stream, and the committed results of the rule that chose the
default smoothness."""

from __future__ import annotations

import functools
import json
import logging
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from canrig_jax import inverse
from canrig_jax.inverse._solve import HISTORY_FRAMES
from canrig_jax.inverse._temporal import (
    _decreases,
    _residuals,
    _take_terms,
    difference_bands,
    weighted_difference_bands,
)
from canrig_jax.papers import inverse_rig
from canrig_jax.rig import BlendshapeRig, evaluate_batch

ALPHA, SMOOTHNESS, VELOCITY = 0.1, 5.0, 0.5
RESULTS = Path(__file__).parents[2] / "experiments" / "results" / "inverse_rig" / "results.json"


@pytest.fixture(scope="module")
def take():
    """(problem, noisy targets (T, V, 3)): a small linear rig (6 shapes, 40 vertices, cm) and
    smooth weight curves with noise of variance 0.03 cm^2."""
    rng = np.random.default_rng(0)
    rig = BlendshapeRig(
        rng.normal(size=(40, 3)).astype(np.float32), rng.normal(size=(6, 40, 3)).astype(np.float32)
    )
    seconds = np.linspace(0.0, 1.0, 9)[:, None]
    truth = 0.5 + 0.5 * np.sin(2 * np.pi * (seconds + np.arange(6) / 6))
    noisy = np.asarray(evaluate_batch(rig, truth)) + rng.normal(0, np.sqrt(0.03), (9, 40, 3))
    return inverse.prepare(rig), noisy.astype(np.float32)


def _streamed(problem, targets, method, lag):
    stream = inverse.Stream(problem, method, lag=lag)
    out = [s for s in map(stream, targets) if s is not None] + stream.flush()
    assert [int(s.stats["frame"]) for s in out] == list(range(len(targets)))
    return np.stack([np.asarray(s.weights, np.float64) for s in out])


def _window_minimum(problem, targets, fixed, smoothness, velocity):
    """SciPy L-BFGS-B (float64) on the window objective: data + alpha terms of the free
    frames (``targets``), time terms over ``fixed`` (earlier frames, constants) + free."""
    deltas = np.asarray(problem.rig.deltas, np.float64).reshape(problem.n_blendshapes, -1)
    offsets = (np.asarray(targets, np.float64) - np.asarray(problem.neutral)).reshape(
        len(targets), -1
    )
    n, k = offsets.shape[0], deltas.shape[0]
    fixed = np.asarray(fixed, np.float64).reshape(-1, k)

    def energy(x):
        w = x.reshape(n, k)
        residual = w @ deltas - offsets
        all_w = np.concatenate([fixed, w])
        d2, d1 = np.diff(all_w, n=2, axis=0), np.diff(all_w, axis=0)
        e = 0.5 * np.sum(residual**2) + ALPHA * w.sum()
        e += 0.5 * smoothness * np.sum(d2**2) + 0.5 * velocity * np.sum(d1**2)
        g = residual @ deltas.T + ALPHA
        g2 = np.zeros_like(all_w)
        g2[:-2] += d2
        g2[1:-1] -= 2 * d2
        g2[2:] += d2
        g1 = np.zeros_like(all_w)
        g1[1:] += d1
        g1[:-1] -= d1
        g = g + (smoothness * g2 + velocity * g1)[len(fixed) :]
        return e, g.ravel()

    x = minimize(
        energy, np.full(n * k, 0.5), jac=True, method="L-BFGS-B", bounds=[(0, 1)] * (n * k),
        options={"ftol": 1e-15, "gtol": 1e-10, "maxiter": 5000},
    ).x  # fmt: skip
    return x.reshape(n, k)


@pytest.mark.slow
def test_a_lagged_frame_is_the_window_solve_with_the_earlier_frames_fixed(take):
    problem, targets = take
    lag = 2
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=SMOOTHNESS, velocity=VELOCITY, tol=1e-9)
    streamed = _streamed(problem, targets, method, lag)
    for frame in (0, 1, 4, 6):  # the first frames have fewer (or no) fixed frames before them
        fixed = streamed[max(frame - HISTORY_FRAMES, 0) : frame]
        window = targets[frame : frame + lag + 1]
        reference = _window_minimum(problem, window, fixed, SMOOTHNESS, VELOCITY)
        np.testing.assert_allclose(streamed[frame], reference[0], atol=2e-4)


@pytest.mark.slow
def test_a_lag_covering_the_take_is_the_batch_temporal_solve(take):
    problem, targets = take
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=SMOOTHNESS, tol=1e-9)
    batch = np.asarray(inverse.solve_sequence(problem, targets, method).weights)
    np.testing.assert_allclose(_streamed(problem, targets, method, len(targets) - 1), batch,
                               atol=1e-4)  # fmt: skip
    # a take shorter than the lag: everything comes from flush
    short = np.asarray(inverse.solve_sequence(problem, targets[:2], method).weights)
    np.testing.assert_allclose(_streamed(problem, targets[:2], method, 4), short, atol=1e-4)


@pytest.mark.slow
def test_lag_zero_without_time_terms_is_the_warm_started_stream(take):
    problem, targets = take
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=0.0)
    plain = inverse.Stream(problem, method, warm_start=True)
    expected = np.stack([np.asarray(plain(t).weights) for t in targets])
    np.testing.assert_allclose(_streamed(problem, targets, method, 0), expected, atol=1e-5)


def _noisy_take(rig, seed: int) -> np.ndarray:
    """(12, V, 3) float32: the rig at smooth weights (a sine per shape) plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    seconds = np.linspace(0.0, 1.0, 12)[:, None]
    truth = 0.45 + 0.4 * np.sin(2 * np.pi * (seconds + np.arange(rig.n_blendshapes) / 8))
    targets = np.asarray(evaluate_batch(rig, truth))
    return (targets + rng.normal(0, np.sqrt(0.03), targets.shape)).astype(np.float32)


@pytest.mark.slow
def test_blocks_carried_from_entry_reach_the_exact_blocks_window_minimum(synthetic_rig):
    """``stream_blocks="on_entry"`` (the default: each frame's Gauss-Newton block computed
    when it enters the window, carried while it is there) against ``"exact"`` (every block
    recomputed every iteration) on a rig with correctives, where the blocks change with the
    weights: the same weights within 1e-4 at a tight tolerance (at the default tolerance the
    two stop at different points; the experiment compares their RMSE and roughness on the
    Live Link take, ``results.json`` ``temporal``: within 0.1 %)."""
    rig = synthetic_rig
    targets = _noisy_take(rig, 2)
    problem = inverse.prepare(rig)
    assert inverse.TemporalNewton().stream_blocks == "on_entry"
    for tol, atol in ((1e-9, 1e-4),):
        weights = {
            blocks: _streamed(
                problem,
                targets,
                inverse.TemporalNewton(
                    alpha=ALPHA, smoothness=SMOOTHNESS, tol=tol, stream_blocks=blocks
                ),  # fmt: skip
                2,
            )
            for blocks in ("on_entry", "exact")
        }
        np.testing.assert_allclose(weights["on_entry"], weights["exact"], atol=atol)


@pytest.mark.slow
def test_the_full_step_first_reaches_the_searched_window_minimum(synthetic_rig):
    """``stream_steps="newton_first"`` (the default: the full Newton step taken when it
    passes Armijo's test, the line search only when it does not) against ``"searched"``
    (every step length scored in every iteration) on a rig with correctives, lag 2 and lag 0:
    the same weights within 1e-4 at a tight tolerance, and at the default tolerance the same
    energies within 1e-5 relative (the float64 take objective of the streamed weights)."""
    rig = synthetic_rig
    targets = _noisy_take(rig, 4)
    problem = inverse.prepare(rig)
    offsets = (targets - np.asarray(problem.neutral)).reshape(len(targets), -1)
    assert inverse.TemporalNewton().stream_steps == "newton_first"
    for lag, tol in ((2, 1e-9), (0, 1e-9), (2, 1e-5)):
        weights = {
            steps: _streamed(
                problem,
                targets,
                inverse.TemporalNewton(
                    alpha=ALPHA, smoothness=SMOOTHNESS, tol=tol, stream_steps=steps
                ),  # fmt: skip
                lag,
            )
            for steps in ("newton_first", "searched")
        }
        if tol < 1e-6:
            np.testing.assert_allclose(weights["newton_first"], weights["searched"], atol=1e-4)
        energy = {
            steps: float(inverse_rig.take_objective(problem, w, offsets, ALPHA, SMOOTHNESS))
            for steps, w in weights.items()
        }
        assert energy["newton_first"] == pytest.approx(energy["searched"], rel=1e-5)


def test_a_window_from_carried_projections_and_norms_is_the_window_from_offsets(synthetic_rig):
    """A lagged ``Stream`` keeps each frame's M^T o_t and ||o_t||^2, not o_t: its window solve
    (``offsets=None``) against the same window solved from the offsets themselves."""
    problem = inverse.prepare(synthetic_rig)
    targets = _noisy_take(synthetic_rig, seed=4)[:5]
    offsets = (jnp.asarray(targets) - problem.neutral).reshape(len(targets), -1)
    init = jnp.asarray(np.random.default_rng(2).uniform(0, 1, (5, problem.n_blendshapes)))
    init = init.astype(jnp.float32)
    present = jnp.asarray([False, True, True, True, True])  # the oldest frame not there yet
    held = (jnp.arange(5) < HISTORY_FRAMES) | ~present
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=SMOOTHNESS, velocity=VELOCITY)
    carry = method.initial_window_carry(problem, 5 - HISTORY_FRAMES)

    @jax.jit
    def both(offsets, init):
        solve = functools.partial(method.solve_window, problem, init=init, held=held,
                                  present=present, history=HISTORY_FRAMES, carry=carry)  # fmt: skip
        from_offsets, _ = solve(offsets=offsets)
        carried, _ = solve(offsets=None, projections=offsets @ problem.columns.T,
                           offset_sq=jnp.sum(offsets * offsets, axis=1))  # fmt: skip
        return from_offsets, carried

    from_offsets, carried = both(offsets, init)
    assert int(from_offsets.steps) > 1 and int(carried.steps) == int(from_offsets.steps)
    np.testing.assert_allclose(np.asarray(carried.weights), np.asarray(from_offsets.weights),
                               atol=1e-5)  # fmt: skip
    np.testing.assert_allclose(np.asarray(carried.history), np.asarray(from_offsets.history),
                               rtol=1e-5)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(carried.weights[:HISTORY_FRAMES]),
                                  np.asarray(init[:HISTORY_FRAMES]))  # fmt: skip


def test_the_carried_residuals_of_a_trial_are_its_residuals(synthetic_rig):
    """The iteration carries each accepted trial's coefficients and residuals Q a - p from
    ``_decreases`` (W's residuals plus Q (a_trial - a_W)) instead of recomputing them: they
    equal the trial's own, computed from its weights (``_residuals``)."""
    problem = inverse.prepare(synthetic_rig)
    offsets = (jnp.asarray(_noisy_take(synthetic_rig, seed=6)[:4]) - problem.neutral).reshape(4, -1)
    rng = np.random.default_rng(8)
    weights = jnp.asarray(rng.uniform(0, 1, (4, problem.n_blendshapes)), jnp.float32)
    trials = jnp.clip(weights + jnp.asarray(rng.normal(0, 0.2, (3, *weights.shape)), jnp.float32),
                      0.0, 1.0)  # fmt: skip
    method = inverse.TemporalNewton(alpha=ALPHA, smoothness=SMOOTHNESS)
    held = jnp.asarray([True, False, False, False])
    terms = _take_terms(method, problem, offsets, held, None, None, 1)
    a, residual = _residuals(terms, weights)
    _, (coefficients, residuals) = _decreases(terms, weights, trials, a, residual)
    for trial, carried_a, carried_residual in zip(trials, coefficients, residuals, strict=True):
        own_a, own_residual = _residuals(terms, trial)
        np.testing.assert_array_equal(np.asarray(carried_a), np.asarray(own_a))
        scale = float(jnp.max(jnp.abs(terms.projections)))
        np.testing.assert_allclose(np.asarray(carried_residual), np.asarray(own_residual),
                                   atol=1e-5 * scale)  # fmt: skip


def test_two_lagged_streams_share_one_compiled_call(take, caplog):
    """Each frame is one call of one compiled function (dispatch, key and frame counter
    inside it): a second stream with another alpha compiles nothing, and the frames come
    back numbered across ``flush`` and a second take."""
    problem, targets = take
    caplog.set_level(logging.WARNING, logger="jax")
    with jax.log_compiles():
        for alpha in (ALPHA, 2 * ALPHA):
            stream = inverse.Stream(problem, inverse.TemporalNewton(alpha=alpha), lag=2)
            first = [s for s in map(stream, targets[:5]) if s is not None] + stream.flush()
            second = [s for s in map(stream, targets[5:6]) if s is not None] + stream.flush()
            frames = [int(s.stats["frame"]) for s in first + second]
            assert frames == list(range(6)) and stream.frame == 6
    compiled = [r for r in caplog.records if "Compiling jit(stream_lagged_call)" in r.getMessage()]
    assert len(compiled) == 1


def test_the_default_smoothness_is_the_value_the_rule_chose():
    results = json.loads(RESULTS.read_text())
    protocol = results["temporal_protocol"]["ict"]
    assert protocol["rule"].endswith("RULE_temporal.md")
    assert protocol["smoothness_chosen_on"] == "ict validation half"
    chosen = inverse_rig.lowest_error_smoothness(protocol["validation_curve"])["smoothness"]
    assert chosen == protocol["smoothness_cm2"] == inverse.DEFAULT_SMOOTHNESS_CM2
    assert results["temporal_protocol"]["makehuman"]["smoothness_cm2"] == chosen
    # in a rig's own units: cm^2 divided by (cm per unit)^2
    rng = np.random.default_rng(1)
    neutral, deltas = rng.normal(size=(5, 3)), rng.normal(size=(2, 5, 3))
    for units, cm in (("cm", 1.0), ("dm", 10.0), ("mm", 0.1)):
        problem = inverse.prepare(BlendshapeRig(neutral, deltas, units=units))
        value = inverse.TemporalNewton().smoothness_for(problem)
        assert value == pytest.approx(chosen / cm**2)
    assert inverse.TemporalNewton(smoothness=3.0).smoothness_for(problem) == 3.0


def test_the_rule_takes_the_lowest_error_and_the_larger_smoothness_on_a_tie():
    sweep = [
        {"smoothness": 0.0, "rmse_mean_mm": 1.0},
        {"smoothness": 10.0, "rmse_mean_mm": 0.8},
        {"smoothness": 100.0, "rmse_mean_mm": 0.8},
        {"smoothness": 1000.0, "rmse_mean_mm": 0.99},
    ]
    assert inverse_rig.lowest_error_smoothness(sweep)["smoothness"] == 100.0
    assert inverse_rig.lowest_error_smoothness(sweep[:1])["smoothness"] == 0.0
    with pytest.raises(ValueError, match="sweep"):
        inverse_rig.lowest_error_smoothness(sweep[1:])
    with pytest.raises(ValueError, match="sweep"):
        inverse_rig.lowest_error_smoothness([*sweep, {"smoothness": 3.0, "rmse_mean_mm": np.nan}])


def test_weighted_bands_of_unit_rows_are_the_difference_bands():
    for n, order in ((1, 2), (2, 2), (5, 2), (5, 1), (1, 1)):
        rows = np.ones(max(n - order, 0), np.float32)
        np.testing.assert_allclose(
            np.asarray(weighted_difference_bands(jnp.asarray(rows), n, order)),
            difference_bands(n, order),
        )
    # a dropped row: the bands of the remaining rows of Delta
    d = np.diff(np.eye(5), n=2, axis=0)
    c = np.array([1.0, 0.0, 1.0])
    dense = d.T @ np.diag(c) @ d
    bands = np.asarray(weighted_difference_bands(jnp.asarray(c, jnp.float32), 5, 2))
    for offset in range(3):
        np.testing.assert_allclose(bands[offset][: 5 - offset], np.diag(dense, offset))


def test_bad_lag_input_is_named_before_compiling(take):
    problem, _ = take
    temporal = inverse.TemporalNewton(alpha=ALPHA)
    for kwargs, method, argument in [
        ({"lag": -1}, temporal, "lag"),
        ({"lag": True}, temporal, "lag"),
        ({"lag": 2}, inverse.QuarticNewton(alpha=ALPHA), "lag"),
        ({"lag": 2}, inverse.TemporalNewton(window=10), "window"),
        ({"lag": 2, "warm_start": False}, temporal, "warm_start"),
    ]:
        with pytest.raises(ValueError, match=argument):
            inverse.Stream(problem, method, **kwargs)
    with pytest.raises(ValueError, match="stream_blocks"):
        inverse.TemporalNewton(stream_blocks="stale")
    with pytest.raises(ValueError, match=r"stream_steps: expected one of .*newton_first"):
        inverse.TemporalNewton(stream_steps="armijo")
    with pytest.raises(ValueError, match="flush"):
        inverse.Stream(problem, temporal).flush()
