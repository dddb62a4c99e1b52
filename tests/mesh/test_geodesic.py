"""Geodesics on the whole ICT head: the bridged edge graph reaches the floating parts (teeth,
gums, eyelashes) from the skin without shortcuts between skin vertices."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from canrig_jax.data import load_ict
from canrig_jax.mesh import bridged_edge_graph, edge_graph, weighted_geodesic_distance


@pytest.fixture(scope="module")
def head(data_dir):
    model = load_ict(data_dir, parts=None)
    vertices, faces = np.asarray(model.neutral, np.float64), np.asarray(model.faces)
    plain = edge_graph(vertices, faces)
    _, label = connected_components(plain, directed=False)
    main = label == np.argmax(np.bincount(label))
    return vertices, faces, plain, bridged_edge_graph(vertices, faces), main


def test_every_vertex_reaches_the_main_component(head):
    vertices, _, plain, bridged, main = head
    rng = np.random.default_rng(0)
    sources = rng.choice(np.flatnonzero(~main), 40, replace=False)
    target = np.flatnonzero(main)[:: max(1, main.sum() // 200)]
    assert np.isinf(weighted_geodesic_distance(plain, sources)[:, target]).all()
    bridged_distance = weighted_geodesic_distance(bridged, sources)[:, target]
    assert np.isfinite(bridged_distance).all()
    # a path is never shorter than the straight line between its ends
    straight = np.linalg.norm(vertices[sources][:, None] - vertices[target][None], axis=-1)
    assert (bridged_distance >= straight - 1e-4).all()


def test_exit_edges_go_to_the_nearest_main_vertex(head):
    vertices, _, plain, bridged, main = head
    exits = (bridged - plain).tocoo()
    assert exits.nnz == (~main).sum()  # one per vertex off the main component
    assert not main[exits.row].any() and main[exits.col].all()  # out of the small parts only
    main_points = vertices[main]
    for row, length in list(zip(exits.row, exits.data, strict=True))[::97]:
        nearest = np.linalg.norm(main_points - vertices[row], axis=1).min()
        np.testing.assert_allclose(length, nearest, rtol=1e-6, atol=1e-9)


def test_no_shortcut_between_main_vertices(head):
    _, _, plain, bridged, main = head
    sources = np.flatnonzero(main)[::997][:20]
    np.testing.assert_array_equal(
        weighted_geodesic_distance(bridged, sources)[:, main],
        weighted_geodesic_distance(plain, sources)[:, main],
    )
