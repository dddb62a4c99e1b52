"""The WPSE per-vertex metric against its definition (Seol et al., eq. (6))."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrig_jax.wpse import blendshape_metric
from canrig_jax.wpse._metric import (
    dot_width,
    euclidean_metric,
    gaussian_kernel,
    pairwise_pose_distance_sq,
    pose_distance_sq,
)


def test_metric_is_normalised_offset_length(tiny_rig):
    deltas = np.asarray(tiny_rig.deltas, np.float64)
    alpha = blendshape_metric(deltas, epsilon=1e-3)
    length = np.linalg.norm(deltas, axis=2).T + 1e-3 * np.linalg.norm(deltas, axis=2).max()
    np.testing.assert_allclose(alpha, length / length.sum(1, keepdims=True), rtol=1e-5)
    np.testing.assert_allclose(alpha.sum(axis=1), 1.0, rtol=1e-5)
    assert np.all(alpha > 0)


def test_unmoved_vertex_gets_uniform_metric():
    deltas = np.zeros((3, 2, 3))
    deltas[0, 0] = [1.0, 0.0, 0.0]
    alpha = blendshape_metric(deltas)
    np.testing.assert_allclose(alpha[1], 1 / 3, rtol=1e-6)


@pytest.mark.slow
@settings(max_examples=20, deadline=None)
@given(st.integers(1, 6), st.sampled_from([1, 5, 16, 17, 33, 50, 64, 70]), st.integers(0, 10_000))
def test_distances_match_a_loop(s, p, seed):
    """Also past the widths the product is padded to (``dot_width``): padding is exact."""
    rng = np.random.default_rng(seed)
    k = 4
    metric = rng.uniform(0, 1, (s, k)).astype(np.float32)
    poses = rng.uniform(0, 1, (p, k)).astype(np.float32)
    w = rng.uniform(0, 1, k).astype(np.float32)
    expected = np.array(
        [
            [sum(metric[v, j] * (w[j] - poses[i, j]) ** 2 for j in range(k)) for i in range(p)]
            for v in range(s)
        ]
    )
    np.testing.assert_allclose(pose_distance_sq(metric, w, poses), expected, rtol=1e-5, atol=1e-6)
    pair = np.asarray(pairwise_pose_distance_sq(metric, poses))
    for i in range(min(p, 5)):
        np.testing.assert_allclose(
            pair[:, i], pose_distance_sq(metric, poses[i], poses), rtol=1e-5, atol=1e-6
        )


@pytest.mark.parametrize("p", [1, 10, 16, 17, 32, 48, 50, 64, 65, 100])
def test_dot_width_covers_every_edit(p):
    width = dot_width(p)
    assert p <= width < p + 32
    assert width % 16 == 0


def test_euclidean_metric_and_kernel():
    w, poses = np.array([0.0, 1.0]), np.array([[1.0, 1.0], [0.0, 0.0]])
    r2 = pose_distance_sq(euclidean_metric(2), w, poses)
    np.testing.assert_allclose(r2, [[1.0, 1.0]])
    np.testing.assert_allclose(gaussian_kernel(r2, 2.0), np.exp(-1 / 8) * np.ones((1, 2)))


@pytest.mark.parametrize("epsilon", [0.0, -1.0, np.nan])
def test_bad_epsilon(epsilon, tiny_rig):
    with pytest.raises(ValueError, match="epsilon"):
        blendshape_metric(tiny_rig.deltas, epsilon)
