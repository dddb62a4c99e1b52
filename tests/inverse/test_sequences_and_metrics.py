"""Whole takes (vmap and warm-started scan) and the paper's metrics, on the real rig."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.inverse import roughness
from canrig_jax.inverse._metrics import frame_metrics
from canrig_jax.rig import evaluate


@pytest.fixture(scope="module")
def take(ict_quartic, ict_quartic_problem, livelink_weights):
    weights = livelink_weights[60:64]
    targets = np.asarray(jax.jit(jax.vmap(evaluate, (None, 0)))(ict_quartic, weights))
    return ict_quartic, ict_quartic_problem, weights, targets


@pytest.mark.slow
def test_warm_started_take_equals_a_loop_of_single_frame_solves(take):
    _, problem, _, targets = take
    method = inverse.QuarticCD(alpha=0.5, passes=2)
    sequence = inverse.solve_sequence(problem, targets, method, warm_start=True)
    single = jax.jit(lambda b, w: inverse.solve(problem, b, method, init=w).weights)
    previous = np.zeros(problem.n_blendshapes, np.float32)
    for t, target in enumerate(targets):
        previous = np.asarray(single(target, previous))
        np.testing.assert_allclose(np.asarray(sequence.weights[t]), previous, atol=1e-5)


def test_frame_metrics_match_their_definitions(take):
    rig, _, weights, targets = take
    noisy = np.clip(weights + 0.05, 0, 1)
    metrics = frame_metrics(rig, noisy, targets)
    meshes = np.stack([np.asarray(evaluate(rig, w), np.float64) for w in noisy])
    distance_mm = np.linalg.norm(meshes - targets, axis=-1) * 10.0
    np.testing.assert_allclose(metrics["rmse_mm"], np.sqrt((distance_mm**2).mean(1)), rtol=1e-4)
    np.testing.assert_allclose(metrics["p95_mm"], np.percentile(distance_mm, 95, axis=1), rtol=1e-4)
    np.testing.assert_array_equal(metrics["cardinality"], (noisy > 1e-3).sum(1))
    np.testing.assert_allclose(metrics["l1"], np.abs(noisy).sum(1), rtol=1e-6)


def test_roughness_is_the_summed_squared_second_difference():
    rng = np.random.default_rng(0)
    w = rng.uniform(size=(7, 3))
    expected = sum(
        (w[t - 1, i] - 2 * w[t, i] + w[t + 1, i]) ** 2 for t in range(1, 6) for i in range(3)
    )
    assert roughness(w) == pytest.approx(expected)
    # a take moving linearly in time has no roughness
    assert roughness(np.linspace(0, 1, 9)[:, None] * np.ones((1, 4))) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="weights"):
        roughness(w[:2])


def test_metrics_are_in_millimetres_whatever_the_rig_unit(take):
    rig, _, weights, _ = take
    linear = rig.linear()
    noisy = np.clip(weights + 0.05, 0, 1)
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(linear, weights))
    in_cm = frame_metrics(linear, noisy, clean)["rmse_mm"]
    # the same head and targets in decimetres: the same millimetres
    dm = type(rig)(rig.neutral / 10, rig.deltas / 10, (), rig.names, units="dm")
    np.testing.assert_allclose(frame_metrics(dm, noisy, clean / 10)["rmse_mm"], in_cm, rtol=1e-4)
    # a rig whose unit is left at the default (cm) reports 10x too little: what units fix
    wrong = type(rig)(rig.neutral / 10, rig.deltas / 10, (), rig.names)
    np.testing.assert_allclose(
        frame_metrics(wrong, noisy, clean / 10)["rmse_mm"], in_cm / 10, rtol=1e-4
    )
    with pytest.raises(ValueError, match="units"):
        type(rig)(rig.neutral, rig.deltas, units="inch")
