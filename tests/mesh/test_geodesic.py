"""Geodesics on the whole ICT head: the bridged edge graph reaches the floating parts (teeth,
gums, eyelashes) from the skin without shortcuts between skin vertices."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from canrig_jax.data import load_ict
from canrig_jax.mesh import (
    attached_edge_graph,
    bridged_edge_graph,
    edge_graph,
    weighted_geodesic_distance,
)


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


MOUTH_INTERIOR = ("Mouth socket", "Gums and tongue", "Teeth")


@pytest.fixture(scope="module")
def attached(head, data_dir):
    """The bridged head with the mouth interior made one-way exits onto the Face part."""
    vertices, _, _, bridged, _ = head
    model = load_ict(data_dir, parts=None)
    interior, face = model.part_mask(MOUTH_INTERIOR), model.part_mask("Face")
    return attached_edge_graph(bridged, vertices, interior, face), interior, face


def test_attached_parts_exit_straight_onto_the_nearest_target(head, attached):
    vertices, _, _, bridged, _ = head
    graph, interior, face = attached
    coo = graph.tocoo()
    assert not (interior[coo.col] & ~interior[coo.row]).any()  # nothing enters from outside

    def to_face(g):  # (interior,) path length from each interior vertex to the nearest face one
        paths_in = g.T.tocsr()
        return dijkstra(paths_in, indices=np.flatnonzero(face), min_only=True)[interior]

    straight, _ = cKDTree(vertices[face]).query(vertices[interior])
    after, before = to_face(graph), to_face(bridged)
    # one straight step through the mouth cavity, never longer than along the socket wall
    np.testing.assert_allclose(after, straight, rtol=1e-6, atol=1e-6)
    assert (after <= before + 1e-6).all()
    # within a 4 cm mask radius of the face skin: ~68% of the interior before, ~95% after
    assert (before < 4.0).mean() < 0.75 and (after < 4.0).mean() > 0.9
    rng = np.random.default_rng(1)
    sources = rng.choice(np.flatnonzero(interior), 20, replace=False)
    paths = weighted_geodesic_distance(graph, sources)
    lines = np.linalg.norm(vertices[sources][:, None] - vertices[None], axis=-1)
    assert (paths >= lines - 1e-4).all()  # no path beats the straight line


def test_attached_keeps_distances_outside_the_attached_parts(head, attached):
    _, _, _, bridged, _ = head
    graph, interior, _ = attached
    sources = np.flatnonzero(~interior)[::701]
    before = weighted_geodesic_distance(bridged, sources)[:, ~interior]
    np.testing.assert_array_equal(weighted_geodesic_distance(graph, sources)[:, ~interior], before)
    assert np.isfinite(before).mean() > 0.5  # the check covers the skin, not just inf == inf


@pytest.mark.bad_input
def test_attached_edge_graph_refuses_bad_masks(head, attached):
    vertices, _, _, bridged, _ = head
    _, interior, face = attached
    with pytest.raises(ValueError, match="attach"):
        attached_edge_graph(bridged, vertices, interior[:-1], face)
    with pytest.raises(ValueError, match="attach"):
        attached_edge_graph(bridged, vertices, interior.astype(int), face)
    with pytest.raises(ValueError, match="onto"):
        attached_edge_graph(bridged, vertices, interior, np.zeros_like(face))
    with pytest.raises(ValueError, match="onto"):
        attached_edge_graph(bridged, vertices, interior, face | interior)
    with pytest.raises(ValueError, match="graph"):
        attached_edge_graph(bridged[:-1, :-1], vertices, interior, face)
