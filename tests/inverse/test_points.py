"""Sparse targets: ``inverse.prepare(rig, points=...)`` (vertex subsets and barycentric points)
and ``mesh.bind_points`` (a landmark layout bound to a head by the project's registration)."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from canrig_jax import inverse
from canrig_jax.mesh import SurfaceMap, bind_points
from canrig_jax.rig import evaluate

METHOD = inverse.QuarticNewton(alpha=0.01, iterations=60, tol=1e-7)


@pytest.fixture(scope="module")
def poses(synthetic_rig):
    rng = np.random.default_rng(5)
    weights = rng.uniform(0, 1, (4, synthetic_rig.n_blendshapes)).astype(np.float32)
    weights[weights < 0.3] = 0.0
    return weights


def _barycentric(rig, n, seed=0):
    rng = np.random.default_rng(seed)
    triangles = rng.choice(np.asarray(rig.faces).shape[0], n, replace=False)
    weights = rng.dirichlet(np.ones(3), n)
    return triangles, weights


def test_the_rig_at_points_is_the_rig_interpolated_at_them(synthetic_rig, poses):
    """Vertex subsets and barycentric points: the point rig's mesh is the full rig's mesh
    (``evaluate``) at the points, for every pose, correctives included."""
    rig = synthetic_rig
    vertices = np.random.default_rng(1).choice(rig.n_vertices, 30, replace=False)
    triangles, weights = _barycentric(rig, 25)
    corners = np.asarray(rig.faces)[triangles]
    for points, at in (
        (vertices, lambda mesh: mesh[vertices]),
        ((triangles, weights), lambda mesh: np.einsum("njd,nj->nd", mesh[corners], weights)),
    ):
        problem = inverse.prepare(rig, points=points)
        assert problem.n_vertices == (30 if points is vertices else 25)
        for w in poses:
            full = np.asarray(evaluate(rig, w), np.float64)
            np.testing.assert_allclose(
                np.asarray(evaluate(problem.rig, w)), at(full), rtol=1e-5, atol=1e-5
            )


def test_every_vertex_as_a_point_is_the_dense_solve(synthetic_rig, poses):
    rig = synthetic_rig
    target = np.asarray(evaluate(rig, poses[0]))
    dense = inverse.solve(inverse.prepare(rig), target, METHOD)
    points = inverse.prepare(rig, points=np.arange(rig.n_vertices))
    sparse = inverse.solve(points, target, METHOD)
    np.testing.assert_allclose(np.asarray(sparse.weights), np.asarray(dense.weights), atol=1e-5)


@pytest.mark.slow
def test_a_few_points_recover_a_clean_pose(synthetic_rig, poses):
    """60 barycentric points of the sheet determine the 8 weights of a noise-free pose (and
    the solve, batched or not, is the same method on the smaller problem)."""
    rig = synthetic_rig
    triangles, weights = _barycentric(rig, 60, seed=3)
    problem = inverse.prepare(rig, points=(triangles, weights))
    corners = np.asarray(rig.faces)[triangles]
    meshes = np.asarray(jax.vmap(evaluate, (None, 0))(rig, poses))
    targets = np.einsum("tnjd,nj->tnd", meshes[:, corners], weights).astype(np.float32)
    solution = inverse.solve_sequence(problem, targets, inverse.QuarticNewton(alpha=0.0))
    np.testing.assert_allclose(np.asarray(solution.weights), poses, atol=2e-3)


def test_bind_points_recovers_a_known_placement():
    """A surface moved by a known similarity binds back onto itself: each point lands on its
    own vertex (barycentric interpolation gives the vertex back)."""
    from canrig_jax.data import load_mediapipe_face

    try:
        face = load_mediapipe_face()
    except FileNotFoundError:
        pytest.skip("no data folder")
    vertices = face.neutral.astype(np.float64)
    rotation = Rotation.from_euler("xyz", [4, -6, 3], degrees=True).as_matrix()
    moved = (0.9 * vertices @ rotation.T + [0.5, -0.3, 0.2]).astype(np.float32)
    binding, fit = bind_points(moved, vertices, face.faces)
    assert isinstance(binding, SurfaceMap) and binding.n_points == 468
    assert fit.scale == pytest.approx(1 / 0.9, rel=1e-3)
    landed = np.einsum("njd,nj->nd", vertices[face.faces[binding.triangle]], binding.barycentric)
    assert np.abs(landed - vertices).max() < 1e-3  # cm
    with pytest.raises(ValueError, match="target_triangles"):
        bind_points(moved, vertices, face.faces, target_triangles=np.zeros(len(face.faces), bool))


@pytest.mark.bad_input
def test_points_outside_the_mesh_are_named(synthetic_rig):
    rig = synthetic_rig
    f = np.asarray(rig.faces).shape[0]
    for points in (
        np.array([0, rig.n_vertices]),
        np.array([-1, 3]),
        np.array([0.5, 1.0]),
        (np.array([0, f]), np.full((2, 3), 1 / 3)),
        (np.array([0, 1]), np.array([[0.5, 0.6, -0.1], [1 / 3, 1 / 3, 1 / 3]])),
        (np.array([0, 1]), np.array([[0.5, 0.6, 0.1], [1 / 3, 1 / 3, 1 / 3]])),
        SurfaceMap(np.array([0]), np.full((1, 3), 1 / 3), np.asarray(rig.faces), 7, np.zeros(1)),
    ):
        with pytest.raises(ValueError, match="points"):
            inverse.prepare(rig, points=points)
    # the targets of a point problem are the points
    problem = inverse.prepare(rig, points=np.arange(10))
    with pytest.raises(ValueError, match=r"target: expected shape \(10, 3\)"):
        inverse.solve(problem, np.asarray(rig.neutral), METHOD)
