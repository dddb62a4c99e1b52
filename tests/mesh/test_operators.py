"""Mesh operators: robust Laplacian and mass, eigenbasis, frames, gradients, disk cache."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import canrig_jax.mesh._operators as ops_module  # patched: the cache's compute step
from canrig_jax.data import FACE, load_ict, load_mediapipe_face
from canrig_jax.mesh import connected_components, decimate
from canrig_jax.mesh._operators import compute_geometry, mesh_geometry


@pytest.fixture(scope="module")
def mediapipe(data_dir):
    face = load_mediapipe_face(data_dir)
    return face.neutral.astype(np.float64), face.faces


@pytest.fixture(scope="module")
def decimated_head(data_dir):
    """The whole ICT head (56 components) decimated to ~3,000 vertices."""
    head = load_ict(data_dir)
    remeshed = decimate(head.neutral, head.faces, 3000)
    return remeshed.vertices, remeshed.faces


def _triangle_areas(vertices, faces):
    cross = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    return 0.5 * np.linalg.norm(cross, axis=1)


def _grid(n=6):
    """A planar, Delaunay, right-triangle grid (synthetic: algebra checks only)."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1.3, n))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [(a, b, d), (a, d, c)]
    return vertices, np.array(faces)


def _cotan_laplacian(vertices, faces):
    """Textbook cotangent Laplacian (positive semi-definite), an independent reference."""
    n = vertices.shape[0]
    rows, cols, values = [], [], []
    for k in range(3):
        i, j, o = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], faces[:, k]
        u, v = vertices[i] - vertices[o], vertices[j] - vertices[o]
        cot = np.sum(u * v, 1) / np.linalg.norm(np.cross(u, v), axis=1)
        rows += [i, j]
        cols += [j, i]
        values += [-0.5 * cot, -0.5 * cot]
    off = sp.csr_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), (n, n)
    )
    return off - sp.diags(np.asarray(off.sum(axis=1)).ravel())


# -- bad input --------------------------------------------------------------------------------


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "mutate, name",
    [
        (lambda v, f: (v, np.where(f == 5, len(v), f)), "faces"),
        (lambda v, f: (v, f - 1), "faces"),
        (lambda v, f: (np.where(np.arange(len(v))[:, None] == 3, np.nan, v), f), "vertices"),
        (lambda v, f: (v[:, :2], f), "vertices"),
        (lambda v, f: (v, f[:, :2]), "faces"),
        (lambda v, f: (v, f[:0]), "faces"),
        (lambda v, f: (v, f.astype(np.float64)), "faces"),
    ],
)
def test_bad_mesh_raises_naming_the_argument(mediapipe, mutate, name):
    vertices, faces = mutate(*mediapipe)
    with pytest.raises(ValueError, match=f"^{name}:"):
        mesh_geometry(vertices, faces, k=4, cache=False)


def test_bad_k_raises(mediapipe):
    with pytest.raises(ValueError, match="^k:"):
        mesh_geometry(*mediapipe, k=-1, cache=False)
    with pytest.raises(ValueError, match="^k:"):
        mesh_geometry(*mediapipe, k=10_000, cache=False)


def test_isolated_vertices_get_zero_mass_and_are_reported(mediapipe):
    vertices, faces = mediapipe
    extra = np.concatenate([vertices, vertices[:1] + 100.0, vertices[:1] - 50.0])
    plain = compute_geometry(vertices, faces, k=20)
    repaired = compute_geometry(extra, faces, k=20)
    n = len(vertices)
    assert repaired.isolated_vertices.tolist() == [n, n + 1]
    assert np.all(repaired.mass[n:] == 0)
    assert np.all(repaired.eigenvectors[n:] == 0)
    assert repaired.laplacian[n:].nnz == 0 and repaired.gradient_x[n:].nnz == 0
    assert repaired.n_components == plain.n_components == 1
    np.testing.assert_allclose(repaired.mass[:n], plain.mass)
    np.testing.assert_allclose(repaired.eigenvalues, plain.eigenvalues, rtol=1e-6, atol=1e-9)
    assert abs(repaired.laplacian[:n, :n] - plain.laplacian).max() < 1e-12


def test_zero_area_triangle_is_handled(mediapipe):
    vertices, faces = mediapipe
    # a sliver: a new vertex exactly at the midpoint of an existing edge, in a new triangle
    a, b = faces[0, 0], faces[0, 1]
    vertices = np.concatenate([vertices, 0.5 * (vertices[a] + vertices[b])[None]])
    faces = np.concatenate([faces, [[a, b, len(vertices) - 1]]])
    geometry = compute_geometry(vertices, faces, k=8)
    assert geometry.n_degenerate_faces == 1
    for array in (geometry.mass, geometry.eigenvalues, geometry.eigenvectors, geometry.frames):
        assert np.all(np.isfinite(array))
    assert np.all(np.isfinite(geometry.laplacian.data)) and np.all(geometry.mass > 0)


# -- Laplacian and mass -----------------------------------------------------------------------


def test_laplacian_equals_cotan_on_a_delaunay_grid():
    vertices, faces = _grid()
    geometry = compute_geometry(vertices, faces, k=0)
    assert abs(geometry.laplacian - _cotan_laplacian(vertices, faces)).max() < 1e-6
    np.testing.assert_allclose(geometry.mass.sum(), _triangle_areas(vertices, faces).sum())


def test_laplacian_and_mass_on_the_ict_face(data_dir):
    face = load_ict(data_dir, parts=FACE)
    geometry = compute_geometry(face.neutral, face.faces, k=0)
    laplacian = geometry.laplacian
    assert abs(laplacian - laplacian.T).max() < 1e-10
    assert np.abs(np.asarray(laplacian.sum(axis=1))).max() < 1e-8
    off_diagonal = laplacian - sp.diags(laplacian.diagonal())
    assert off_diagonal.max() <= 1e-12  # intrinsic Delaunay: non-negative cotan weights
    assert np.all(geometry.mass > 0)
    area = _triangle_areas(geometry.vertices, geometry.faces).sum()
    assert abs(geometry.mass.sum() / area - 1) < 1e-3


# -- eigenbasis -------------------------------------------------------------------------------


def test_one_zero_eigenvalue_per_component_on_the_ict_head(decimated_head):
    vertices, faces = decimated_head
    geometry = compute_geometry(vertices, faces, k=80)
    labels = connected_components(faces, len(vertices))
    assert geometry.n_components == len(np.unique(labels)) == 56
    assert geometry.n_zero_eigenvalues == 56
    values, vectors, mass = geometry.eigenvalues, geometry.eigenvectors, geometry.mass
    assert np.all(np.diff(values) >= -1e-12)
    # M-orthonormal, and L phi = lambda M phi
    np.testing.assert_allclose(vectors.T @ (mass[:, None] * vectors), np.eye(80), atol=1e-8)
    residual = geometry.laplacian @ vectors - mass[:, None] * vectors * values
    assert np.abs(residual).max() < 1e-6 * np.abs(geometry.laplacian @ vectors).max() + 1e-9
    # the zero eigenvectors span the component indicator functions
    zero = vectors[:, :56]
    for label in np.unique(labels):
        indicator = (labels == label).astype(float)
        projection = zero @ (zero.T @ (mass * indicator))
        np.testing.assert_allclose(projection, indicator, atol=1e-6)
    # a clear spectral gap separates them from the first non-zero eigenvalue
    assert values[56] * geometry.total_area > 1e3 * ops_module.ZERO_EIGENVALUE_TOL


@pytest.mark.slow  # 25-40 s: a dense eigensolve of the whole decimated head
def test_per_component_eigenpairs_match_one_dense_solve_of_the_whole_head(decimated_head):
    """Solving each of the 56 parts on its own and keeping the k smallest of the union gives
    the spectrum of the whole (block-diagonal) problem, and the same diffusion projector."""
    vertices, faces = decimated_head
    geometry = compute_geometry(vertices, faces, k=128)
    scale = geometry.mass**-0.5
    whole = scale[:, None] * geometry.laplacian.toarray() * scale[None, :]
    values, vectors = np.linalg.eigh(whole)
    reference = np.where(values[:128] * geometry.total_area < 1e-6, 0.0, values[:128])
    np.testing.assert_allclose(geometry.eigenvalues, reference, rtol=1e-7, atol=1e-8)
    # Phi Phi^T M over the first 120 pairs (not splitting a near-degenerate pair at the cut)
    assert values[120] - values[119] > 1e-6 * values[119]
    phi = scale[:, None] * vectors[:, :120]
    projector = geometry.eigenvectors[:, :120] @ (geometry.eigenvectors[:, :120].T * geometry.mass)
    np.testing.assert_allclose(projector, phi @ (phi.T * geometry.mass), atol=1e-8)


def test_shift_invert_eigenvalues_match_a_dense_solve(data_dir):
    eyeball = load_ict(data_dir, parts=("Eyeball left",))  # 1,570 vertices: sparse path
    geometry = compute_geometry(eyeball.neutral, eyeball.faces, k=12)
    scale = np.diag(geometry.mass**-0.5)
    dense = np.linalg.eigvalsh(scale @ geometry.laplacian.toarray() @ scale)[:12]
    np.testing.assert_allclose(geometry.eigenvalues, dense, rtol=1e-6, atol=1e-9)
    assert geometry.n_zero_eigenvalues == geometry.n_components  # eyeball and iris: 2


# -- frames and gradients ---------------------------------------------------------------------


def test_frames_are_orthonormal_and_right_handed(mediapipe):
    geometry = compute_geometry(*mediapipe, k=0)
    frames = geometry.frames
    np.testing.assert_allclose(
        frames @ np.swapaxes(frames, 1, 2), np.broadcast_to(np.eye(3), frames.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    # normals point the same way as the faces around them (area-weighted)
    cross = np.cross(
        geometry.vertices[geometry.faces[:, 1]] - geometry.vertices[geometry.faces[:, 0]],
        geometry.vertices[geometry.faces[:, 2]] - geometry.vertices[geometry.faces[:, 0]],
    )
    agree = np.sum(cross * frames[geometry.faces[:, 0], 2], axis=1) > 0
    assert agree.mean() > 0.98  # all but faces at sharp folds (lip corners)


def test_gradient_of_a_linear_function_is_exact_on_a_plane():
    vertices, faces = _grid()
    rotation = np.linalg.qr(np.random.default_rng(0).standard_normal((3, 3)))[0]
    vertices = vertices @ rotation.T  # a tilted plane
    geometry = compute_geometry(vertices, faces, k=0)
    direction = np.array([0.3, -1.1, 0.7])
    values = vertices @ direction
    tangent = direction - (direction @ rotation[:, 2]) * rotation[:, 2]
    expected_x = geometry.frames[:, 0] @ tangent
    expected_y = geometry.frames[:, 1] @ tangent
    np.testing.assert_allclose(geometry.gradient_x @ values, expected_x, atol=1e-4)
    np.testing.assert_allclose(geometry.gradient_y @ values, expected_y, atol=1e-4)


def test_gradient_on_the_ict_face_matches_the_tangential_gradient(data_dir):
    face = load_ict(data_dir, parts=FACE)
    geometry = compute_geometry(face.neutral, face.faces, k=0)
    direction = np.array([0.2, 0.5, -0.8])
    values = geometry.vertices @ direction
    error = np.hypot(
        geometry.gradient_x @ values - geometry.frames[:, 0] @ direction,
        geometry.gradient_y @ values - geometry.frames[:, 1] @ direction,
    )
    assert np.median(error) < 0.02 * np.linalg.norm(direction)


# -- cache ------------------------------------------------------------------------------------


def test_second_call_loads_from_the_cache(data_dir, tmp_path, monkeypatch):
    face = load_mediapipe_face(data_dir)
    first = mesh_geometry(face.neutral, face.faces, k=32, cache=tmp_path)
    assert not first.from_cache and len(list(tmp_path.glob("operators-*.npz"))) == 1

    def fail(*args, **kwargs):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(ops_module, "compute_geometry", fail)  # the cached path never computes
    second = mesh_geometry(face.neutral, face.faces, k=32, cache=tmp_path)
    assert second.from_cache
    for name in ("mass", "eigenvalues", "eigenvectors", "frames"):
        np.testing.assert_array_equal(getattr(second, name), getattr(first, name))
    for name in ("laplacian", "gradient_x", "gradient_y"):
        assert abs(getattr(second, name) - getattr(first, name)).max() == 0
    assert second.n_zero_eigenvalues == first.n_zero_eigenvalues == 1
    # another k or another mesh is another key
    with pytest.raises(AssertionError, match="recomputed"):
        mesh_geometry(face.neutral, face.faces, k=16, cache=tmp_path)
    with pytest.raises(AssertionError, match="recomputed"):
        mesh_geometry(face.neutral * 1.01, face.faces, k=32, cache=tmp_path)


def test_cache_follows_the_environment_variable(data_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("CANRIG_CACHE", str(tmp_path))
    face = load_mediapipe_face(data_dir)
    mesh_geometry(face.neutral, face.faces, k=4)
    assert len(list(tmp_path.glob("operators-*.npz"))) == 1
    assert mesh_geometry(face.neutral, face.faces, k=4).from_cache
