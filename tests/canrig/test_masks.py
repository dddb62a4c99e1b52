"""Geodesic distances, influence masks and the correlation prior."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from canrig_jax import canrig, mesh
from canrig_jax.canrig import CLAMP, correlation_edge_factor, influence_mask
from canrig_jax.canrig._masks import MIN_EDGE_FACTOR
from canrig_jax.mesh import (
    edge_graph,
    farthest_point_vertices,
    mesh_edges,
    weighted_geodesic_distance,
)


def test_geometry_has_one_home():
    """canrig consumes mesh's graph geometry (not re-derived, and not exported again: the
    one door is ``canrig_jax.mesh``)."""
    from canrig_jax.canrig import _data, _masks

    for name in ("mesh_edges", "edge_graph", "weighted_geodesic_distance"):
        assert getattr(_masks, name) is getattr(mesh, name)
        assert name not in canrig.__all__
    assert _data.farthest_point_vertices is mesh.farthest_point_vertices
    assert "farthest_point_vertices" not in canrig.__all__


def _grid(n=4, m=3, seed=0):
    """A jittered n x m vertex grid, two triangles per cell."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(m, dtype=float), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), rng.normal(0, 0.2, n * m)], axis=1)
    faces = []
    for i in range(n - 1):
        for j in range(m - 1):
            a, b, c, d = i * m + j, (i + 1) * m + j, (i + 1) * m + j + 1, i * m + j + 1
            faces += [(a, b, c), (a, c, d)]
    return vertices, np.array(faces)


def _floyd_warshall(vertices, faces, factor=None):
    v = len(vertices)
    dist = np.full((v, v), np.inf)
    np.fill_diagonal(dist, 0.0)
    for e, (i, j) in enumerate(mesh_edges(faces)):
        w = np.linalg.norm(vertices[i] - vertices[j]) * (1.0 if factor is None else factor[e])
        dist[i, j] = dist[j, i] = w
    for k in range(v):
        dist = np.minimum(dist, dist[:, k : k + 1] + dist[k : k + 1, :])
    return dist


def test_geodesic_distance_matches_floyd_warshall():
    vertices, faces = _grid()
    sources = np.array([0, 5, 11])
    got = weighted_geodesic_distance(edge_graph(vertices, faces), sources)
    np.testing.assert_allclose(got, _floyd_warshall(vertices, faces)[sources], rtol=1e-6)


def test_geodesic_limit_gives_inf_beyond():
    vertices, faces = _grid()
    full = weighted_geodesic_distance(edge_graph(vertices, faces), np.array([0]))
    limited = weighted_geodesic_distance(edge_graph(vertices, faces), np.array([0]), limit=1.5)
    near = full <= 1.5
    np.testing.assert_array_equal(limited[near], full[near])
    assert np.all(np.isinf(limited[full > 1.5 + 1e-6]))


def test_correlation_prior_against_corrcoef():
    vertices, faces = _grid()
    rng = np.random.default_rng(1)
    shapes = vertices + rng.normal(0, 0.1, (12, *vertices.shape))
    shapes[:, 1] = shapes[:, 0] + 0.3  # vertex 1 moves exactly with vertex 0
    factor = correlation_edge_factor(faces, shapes)
    edges = mesh_edges(faces)
    centred = (shapes - shapes.mean(0)).transpose(1, 0, 2).reshape(len(vertices), -1)
    for e, (i, j) in enumerate(edges):
        a, b = centred[i], centred[j]
        corr = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
        assert factor[e] == pytest.approx(max(1 - abs(corr), MIN_EDGE_FACTOR), abs=1e-9)
    assert factor[np.flatnonzero((edges == [0, 1]).all(axis=1))[0]] == MIN_EDGE_FACTOR
    got = weighted_geodesic_distance(edge_graph(vertices, faces, factor), np.array([0, 7]))
    np.testing.assert_allclose(got, _floyd_warshall(vertices, faces, factor)[[0, 7]], rtol=1e-5)


def test_influence_mask_closed_form_and_clamp():
    rng = np.random.default_rng(2)
    distance = rng.uniform(0, 5, (6, 40)).astype(np.float32)
    distance[0, :3] = np.inf
    radius, falloff = rng.uniform(0.5, 3, 6), rng.uniform(1, 6, 6)
    expected = 0.5 * (1 - np.tanh(falloff[:, None] * (distance - radius[:, None])))
    got = np.asarray(influence_mask(distance.T, radius, falloff)).T
    np.testing.assert_allclose(got, np.nan_to_num(expected, nan=0.0), atol=1e-6)
    assert np.all(got[0, :3] == 0.0)
    clamped = np.asarray(influence_mask(distance.T, radius, falloff, CLAMP)).T
    assert np.all(clamped[got < CLAMP] == 0.0)
    np.testing.assert_array_equal(clamped[got >= CLAMP], got[got >= CLAMP])


def test_radius_and_falloff_change_without_recompiling():
    fn = jax.jit(influence_mask)
    distance = np.linspace(0, 4, 50, dtype=np.float32)[:, None]
    a = fn(distance, np.array([1.0], np.float32), np.array([2.0], np.float32))
    compiled = fn._cache_size()  # (jit of the same function shares one cache per process)
    b = fn(distance, np.array([3.0], np.float32), np.array([5.0], np.float32))
    assert fn._cache_size() == compiled
    assert not np.allclose(a, b)


def test_lips_do_not_leak_across_the_mouth_gap(ict_face):
    """A small mask on the upper lip leaves the lower lip at exactly zero (ICT face)."""
    vertices = np.asarray(ict_face.neutral, np.float64)
    jaw = np.linalg.norm(np.asarray(ict_face.deltas[ict_face.names.index("jawOpen")]), axis=1)
    front = (vertices[:, 2] > vertices[:, 2].max() - 3.0) & (np.abs(vertices[:, 0]) < 0.5)
    upper = np.flatnonzero(front & (jaw < 1.0) & (vertices[:, 1] < -1.5) & (vertices[:, 1] > -4))
    lower = np.flatnonzero(front & (jaw > 3.0) & (vertices[:, 1] > -5.0))
    gap = np.linalg.norm(vertices[upper][:, None] - vertices[lower][None], axis=2)
    u, low = np.unravel_index(np.argmin(gap), gap.shape)
    handle, across = upper[u], lower[low]
    assert gap[u, low] < 0.3  # the lips touch: 1-3 mm apart in 3D
    distance = weighted_geodesic_distance(edge_graph(vertices, ict_face.faces), np.array([handle]))
    assert distance[0, across] > 2.0  # the path goes around the mouth corner
    mask = np.asarray(influence_mask(distance.T, np.array([0.5]), np.array([6.0]), CLAMP))[:, 0]
    near_lower = lower[np.linalg.norm(vertices[lower] - vertices[handle], axis=1) < 1.5]
    assert near_lower.size > 5
    assert np.all(mask[near_lower] == 0.0)
    assert mask[handle] > 0.9


@pytest.mark.parametrize("geodesic", [False, True])
def test_farthest_point_order_is_greedy(geodesic):
    """Each new handle is a vertex farthest from those already chosen (distances from an
    independent all-pairs computation)."""
    vertices, faces = _grid(6, 5)
    if geodesic:
        dist, graph = _floyd_warshall(vertices, faces), edge_graph(vertices, faces)
    else:
        dist, graph = np.linalg.norm(vertices[:, None] - vertices[None], axis=2), None
    order = farthest_point_vertices(vertices, 12, start=3, graph=graph)
    assert order[0] == 3 and len(set(order.tolist())) == 12
    for k in range(1, 12):
        gap = dist[order[:k]].min(axis=0)
        assert np.isclose(gap[order[k]], gap.max())


def test_farthest_point_reaches_every_component():
    vertices, faces = _grid()
    shifted = vertices + np.array([100.0, 0.0, 0.0])
    both = np.concatenate([vertices, shifted])
    graph = edge_graph(both, np.concatenate([faces, faces + len(vertices)]))
    order = farthest_point_vertices(both, 2, start=0, graph=graph)
    assert order[1] >= len(vertices)


def test_geodesic_farthest_points_cover_the_ict_face_more_evenly(ict_face):
    """On the ICT face the lips and eyelids touch in 3D: Euclidean farthest points leave
    parts of them far (along the surface) from every handle; geodesic ones do not."""
    vertices = np.asarray(ict_face.neutral, np.float64)
    graph = edge_graph(vertices, ict_face.faces)

    def covering_radius(index):
        return weighted_geodesic_distance(graph, index).min(axis=0).max()

    euclidean = covering_radius(farthest_point_vertices(vertices, 200))
    geodesic = covering_radius(farthest_point_vertices(vertices, 200, graph=graph))
    assert geodesic < 0.85 * euclidean


@pytest.mark.parametrize(
    "n, start, match", [(0, 0, "n:"), (13, 0, "n:"), (3, 12, "start"), (3, 0, "graph")]
)
def test_bad_farthest_point_arguments(n, start, match):
    vertices, faces = _grid()
    smaller_mesh = edge_graph(vertices[:6], faces[:2])
    with pytest.raises(ValueError, match=match):
        farthest_point_vertices(vertices, n, start, graph=smaller_mesh)


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "sources, match",
    [
        (np.array([], np.int64), "sources"),
        (np.array([0, 99]), "sources"),
        (np.array([0.5]), "sources"),
    ],
)
def test_bad_sources(sources, match):
    vertices, faces = _grid()
    with pytest.raises(ValueError, match=match):
        weighted_geodesic_distance(edge_graph(vertices, faces), sources)


def test_bad_mesh_and_factor():
    vertices, faces = _grid()
    with pytest.raises(ValueError, match="faces"):
        edge_graph(vertices, faces + 100)
    with pytest.raises(ValueError, match="edge_factor"):
        edge_graph(vertices, faces, np.ones(3))
    with pytest.raises(ValueError, match="shapes"):
        correlation_edge_factor(faces, vertices[None])
