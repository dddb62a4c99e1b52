"""Remeshing real heads with a data-carrying surface map."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from canrig_jax.data import FACE, load_ict, load_mediapipe_face
from canrig_jax.mesh import connected_components, decimate, flip_quad_split, subdivide
from canrig_jax.mesh._remesh import _closest_on_triangles, closest_surface_points, quad_pairs
from canrig_jax.rig import BlendshapeRig, Corrective, evaluate, remesh_rig


@pytest.fixture(scope="module")
def head(data_dir):
    return load_ict(data_dir)


@pytest.fixture(scope="module")
def decimated(head):
    return decimate(head.neutral, head.faces, 5000)


def _area(vertices, faces):
    cross = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    return 0.5 * np.linalg.norm(cross, axis=1).sum()


def test_closest_surface_points_match_brute_force(data_dir):
    face = load_mediapipe_face(data_dir)
    vertices, faces = face.neutral.astype(np.float64), face.faces
    rng = np.random.default_rng(0)
    points = vertices[rng.integers(0, len(vertices), 60)] + rng.normal(0, 0.3, (60, 3))
    found = closest_surface_points(points, vertices, faces)
    # brute force: dense sampling of every triangle (barycentric grid, step 1/24)
    steps = np.linspace(0, 1, 25)
    u, v = np.meshgrid(steps, steps)
    keep = u + v <= 1
    bary = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)
    samples = np.einsum("sk,fkd->fsd", bary, vertices[faces]).reshape(-1, 3)
    brute = np.array([np.linalg.norm(samples - p, axis=1).min() for p in points])
    assert np.all(found.distance <= brute + 1e-9)
    assert np.all(found.distance >= brute - 0.02)  # the grid's resolution
    surface = np.einsum("nk,nkd->nd", found.barycentric, vertices[faces[found.triangle]])
    np.testing.assert_allclose(np.linalg.norm(surface - points, axis=1), found.distance)
    assert np.all(found.barycentric >= 0)
    np.testing.assert_allclose(found.barycentric.sum(1), 1.0)


def test_decimation_keeps_components_and_carries_data(head, decimated):
    assert abs(decimated.n_vertices - 5000) < 0.05 * 5000
    labels = connected_components(decimated.faces, decimated.n_vertices)
    assert len(np.unique(labels)) == len(np.unique(head.component_labels)) == 56
    # new vertices lie on the original surface, on their own component
    np.testing.assert_allclose(
        decimated.map.carry(head.neutral.astype(np.float64)), decimated.vertices, atol=1e-6
    )
    assert decimated.map.distance.max() < 0.15  # cm: quadric placement snapped back
    source_component = head.component_labels[head.faces[decimated.map.triangle, 0]]
    for label in np.unique(labels):
        assert len(np.unique(source_component[labels == label])) == 1
    # carried deltas: linear interpolation, shape (K, N, 3), and no larger than the source
    deltas = decimated.map.carry(head.deltas)
    assert deltas.shape == (head.deltas.shape[0], decimated.n_vertices, 3)
    assert np.abs(deltas).max() <= np.abs(head.deltas).max() + 1e-6
    # the surface area is kept within 2 %
    assert (
        abs(_area(decimated.vertices, decimated.faces) / _area(head.neutral, head.faces) - 1) < 0.02
    )


def test_carry_matches_the_sparse_matrix(head, decimated):
    values = head.deltas[:3]
    np.testing.assert_allclose(
        decimated.map.carry(values),
        np.stack([decimated.map.matrix() @ v for v in values]),
        rtol=1e-5,
        atol=1e-6,
    )
    scalar = head.neutral[:, 1]
    np.testing.assert_allclose(decimated.map.carry(scalar), decimated.map.matrix() @ scalar)


def test_subdivision_is_exact(data_dir):
    face = load_ict(data_dir, parts=FACE)
    fine = subdivide(face.neutral, face.faces)
    n_edges = fine.n_vertices - face.n_vertices
    assert fine.faces.shape[0] == 4 * face.faces.shape[0]
    edges = np.sort(
        np.concatenate([face.faces[:, [0, 1]], face.faces[:, [1, 2]], face.faces[:, [2, 0]]]), 1
    )
    assert n_edges == len(np.unique(edges, axis=0))
    np.testing.assert_allclose(fine.map.carry(face.neutral.astype(np.float64)), fine.vertices)
    np.testing.assert_allclose(
        _area(fine.vertices, fine.faces), _area(face.neutral, face.faces), rtol=1e-6
    )
    assert np.all(fine.map.distance == 0)


def test_flipped_quad_split_is_the_same_surface(data_dir):
    face = load_ict(data_dir, parts=FACE)
    flipped = flip_quad_split(face.neutral, face.faces)
    changed = np.any(flipped.faces != face.faces, axis=1)
    assert changed.mean() > 0.9
    np.testing.assert_array_equal(flipped.vertices, face.neutral)
    # each quad keeps its four corners, split along the other diagonal
    pairs = quad_pairs(face.faces)
    for before, after in ((face.faces, flipped.faces),):
        quad_before = np.concatenate([before[pairs], before[pairs + 1]], 1)
        quad_after = np.concatenate([after[pairs], after[pairs + 1]], 1)
        for row_b, row_a in zip(quad_before[::97], quad_after[::97], strict=True):
            assert set(row_b) == set(row_a) and len(set(row_b)) == 4
        shared_before = [
            set(a) & set(b) for a, b in zip(before[pairs], before[pairs + 1], strict=True)
        ]
        shared_after = [
            set(a) & set(b) for a, b in zip(after[pairs], after[pairs + 1], strict=True)
        ]
        assert all(
            len(x) == 2 and not (x & y) for x, y in zip(shared_before, shared_after, strict=True)
        )
    assert abs(_area(flipped.vertices, flipped.faces) / _area(face.neutral, face.faces) - 1) < 0.01


def test_remeshed_rig_evaluates_to_the_carried_expressions(data_dir):
    face = load_ict(data_dir, parts=FACE)
    dense = np.zeros((1, face.n_vertices, 3), np.float32)
    dense[0, :100] = 0.1
    rig = BlendshapeRig(
        face.neutral,
        face.deltas,
        (Corrective.from_dense([[0, 1]], dense),),
        face.names,
        face.faces,
    )
    coarse = decimate(face.neutral, face.faces, 2000)
    carried = remesh_rig(rig, coarse)
    assert carried.n_vertices == coarse.n_vertices and carried.n_correctives(2) == 1
    weights = np.zeros(rig.n_blendshapes, np.float32)
    weights[[0, 1, 20]] = (1.0, 0.5, 0.8)
    expected = coarse.map.carry(np.asarray(jax.jit(evaluate)(rig, weights), np.float64))
    np.testing.assert_allclose(np.asarray(evaluate(carried, weights)), expected, atol=1e-5)


def test_remeshed_rig_keeps_the_rig_unit(data_dir):
    """A head in decimetres stays in decimetres on the new mesh (and evaluates there)."""
    face = load_ict(data_dir, parts=FACE)
    rig = BlendshapeRig(face.neutral / 10, face.deltas[:3] / 10, (), face.names[:3], face.faces,
                        units="dm")  # fmt: skip
    coarse = decimate(rig.neutral, face.faces, 1000)
    carried = remesh_rig(rig, coarse)
    assert carried.units == "dm"
    weights = np.array([1.0, 0.5, 0.0], np.float32)
    expected = coarse.map.carry(np.asarray(evaluate(rig, weights), np.float64))
    np.testing.assert_allclose(np.asarray(evaluate(carried, weights)), expected, atol=1e-6)


def test_bad_input(head, decimated):
    vertices = np.concatenate([head.neutral, head.neutral[:1] + 10])
    with pytest.raises(ValueError, match="^vertices:.*isolated"):
        decimate(vertices, head.faces, 5000)
    with pytest.raises(ValueError, match="^target_vertices:"):
        decimate(head.neutral, head.faces, 10**6)
    with pytest.raises(ValueError, match="^faces:"):
        subdivide(head.neutral, head.faces + len(head.neutral))
    with pytest.raises(ValueError, match="^faces:.*quads"):
        flip_quad_split(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="^values:"):
        decimated.map.carry(np.zeros((7, 3)))


def _closest_among_every_candidate(points, vertices, faces, n_candidates=16):
    """``closest_surface_points`` as it was: every candidate (the nearest centroids' triangles,
    then the triangles at the nearest vertex, padded with the first) tested, np.argmin."""
    from scipy.spatial import KDTree

    _, near = KDTree(vertices[faces].mean(axis=1)).query(points, k=n_candidates)
    _, nearest_vertex = KDTree(vertices).query(points)
    ring = [np.flatnonzero((faces == v).any(axis=1)) for v in nearest_vertex]
    width = max(len(r) for r in ring)
    ring = np.stack(
        [np.r_[r, np.full(width - len(r), n[0])] for r, n in zip(ring, near, strict=True)]
    )
    candidates = np.concatenate([near, ring], axis=1)
    tri = vertices[faces[candidates]]
    query = np.broadcast_to(points[:, None], candidates.shape + (3,))
    bary = _closest_on_triangles(query, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    distance = np.linalg.norm(np.einsum("nck,nckd->ncd", bary, tri) - query, axis=-1)
    best = np.argmin(distance, axis=1)
    pick = np.arange(len(points))
    return candidates[pick, best], bary[pick, best], distance[pick, best]


@pytest.mark.parametrize("spread_cm", [0.0, 0.05, 1.0])
def test_closest_surface_points_choose_what_testing_every_candidate_chooses(
    decimated, head, spread_cm
):
    # the decimated head's vertices (on the surface, many at its vertices and edges: ties
    # between neighbouring triangles), and moved off it: the candidates left untested (too
    # far, or tested already) never change the triangle, the weights or the distance
    rng = np.random.default_rng(4)
    points = decimated.vertices + rng.normal(scale=spread_cm, size=decimated.vertices.shape)
    vertices = np.asarray(head.neutral, np.float64)
    found = closest_surface_points(points, vertices, head.faces)
    triangle, barycentric, distance = _closest_among_every_candidate(points, vertices, head.faces)
    np.testing.assert_array_equal(found.triangle, triangle)
    np.testing.assert_array_equal(found.barycentric, barycentric)
    np.testing.assert_array_equal(found.distance, distance)
