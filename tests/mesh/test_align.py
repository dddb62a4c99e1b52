"""Trimmed ICP (Anderson-accelerated) and the closest-point index it reuses."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import load_mediapipe_face
from canrig_jax.mesh import _align, _remesh, similarity_icp
from canrig_jax.mesh._remesh import closest_surface_points


@pytest.fixture(scope="module")
def face(data_dir):
    mp = load_mediapipe_face(data_dir)
    return np.asarray(mp.neutral, np.float64), np.asarray(mp.faces)


def _turn(degrees: float) -> np.ndarray:
    a = np.deg2rad(degrees)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def test_accelerated_icp_reaches_the_plain_alternations_fixed_point(face, monkeypatch):
    """The same trimmed-ICP fixed point with and without extrapolation (``ICP_MEMORY = 0`` is
    plain alternation), in fewer alternations; and the known similarity recovered."""
    vertices, faces = face
    points = vertices[::3]
    size = float(np.ptp(vertices, axis=0).max())
    moved = 1.1 * points @ _turn(8.0).T + np.array([0.02, -0.01, 0.03]) * size
    accelerated = similarity_icp(moved, vertices, faces, trim=1.0, tolerance=1e-10)
    monkeypatch.setattr(_align, "ICP_MEMORY", 0)
    plain = similarity_icp(moved, vertices, faces, trim=1.0, tolerance=1e-10, iterations=1000)
    np.testing.assert_allclose(accelerated.apply(moved), plain.apply(moved), atol=1e-4 * size)
    assert accelerated.iterations < plain.iterations
    # the fit undoes the move: the moved points land back on the surface they came from
    np.testing.assert_allclose(accelerated.apply(moved), points, atol=1e-4 * size)
    assert accelerated.scale == pytest.approx(1 / 1.1, rel=1e-4)


def test_closest_points_follow_the_mesh_not_a_stale_index(face):
    """The kept search trees are keyed by the mesh's content: a mesh changed in place is
    queried afresh, and answers equal a brute-force search over every triangle."""
    vertices, faces = face
    vertices = vertices.copy()
    rng = np.random.default_rng(0)
    queries = vertices[rng.choice(len(vertices), 50)] + 0.01 * rng.normal(size=(50, 3))
    closest_surface_points(queries, vertices, faces)
    vertices *= 1.5  # same array object, other surface
    found = closest_surface_points(queries, vertices, faces)
    tri = vertices[faces]
    every = _remesh._closest_on_triangles(
        np.broadcast_to(queries[:, None], (50, len(faces), 3)), tri[:, 0], tri[:, 1], tri[:, 2]
    )
    distance = np.linalg.norm(np.einsum("nfk,fkd->nfd", every, tri) - queries[:, None], axis=-1)
    np.testing.assert_allclose(found.distance, distance.min(axis=1), atol=1e-12)
