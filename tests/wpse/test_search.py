"""Search of sculpted edits by region of interest (section 4)."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.wpse import blendshape_metric, search_edits


def test_energy_matches_definition_and_is_sorted(tiny_rig):
    rng = np.random.default_rng(0)
    alpha = blendshape_metric(tiny_rig.deltas)
    library = rng.uniform(0, 1, (12, tiny_rig.n_blendshapes)).astype(np.float32)
    query = rng.uniform(0, 1, tiny_rig.n_blendshapes).astype(np.float32)
    roi = np.array([3, 7, 20, 33])
    result = search_edits(alpha, library, query, roi)
    expected = np.array(
        [sum(np.sqrt(np.sum(alpha[v] * (query - p) ** 2)) for v in roi) for p in library]
    )
    np.testing.assert_array_equal(result.indices, np.argsort(expected, kind="stable"))
    np.testing.assert_allclose(result.energies, np.sort(expected), rtol=1e-5)
    tau = float(np.median(expected))
    below = search_edits(alpha, library, query, roi, tau)
    assert np.all(below.energies < tau)
    assert below.indices.size == int(np.sum(expected < tau))


def test_region_ignores_channels_that_do_not_move_it():
    """Two shapes on disjoint vertices: poses differing only in shape 1 are equally close on
    the ROI of shape 0."""
    deltas = np.zeros((2, 4, 3), np.float32)
    deltas[0, :2, 0] = 1.0
    deltas[1, 2:, 1] = 1.0
    alpha = blendshape_metric(deltas, epsilon=1e-6)
    library = np.array([[0.5, 0.0], [0.5, 1.0], [0.0, 0.0]], np.float32)
    result = search_edits(alpha, library, np.array([0.5, 0.5], np.float32), np.array([0, 1]))
    assert set(result.indices[:2].tolist()) == {0, 1}
    assert result.energies[1] < 1e-2 < result.energies[2]


@pytest.mark.bad_input
def test_bad_input(tiny_rig):
    alpha = blendshape_metric(tiny_rig.deltas)
    library = np.zeros((3, tiny_rig.n_blendshapes), np.float32)
    query = np.zeros(tiny_rig.n_blendshapes, np.float32)
    with pytest.raises(ValueError, match="roi"):
        search_edits(alpha, library, query, np.array([], np.int64))
    with pytest.raises(ValueError, match="roi"):
        search_edits(alpha, library, query, np.array([tiny_rig.n_vertices]))
    with pytest.raises(ValueError, match="roi"):
        search_edits(alpha, library, query, np.array([1, 1]))
    with pytest.raises(ValueError, match="query"):
        search_edits(alpha, library, query[:-1], np.array([0]))
    with pytest.raises(ValueError, match="library"):
        search_edits(alpha, library[:, :-1], query, np.array([0]))
    with pytest.raises(ValueError, match="tau"):
        search_edits(alpha, library, query, np.array([0]), tau=0.0)
