"""MediaPipe canonical face against its raw OBJ."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import connected_components

from canrig_jax.data import load_mediapipe_face


@pytest.fixture(scope="module")
def face(data_dir):
    return load_mediapipe_face(data_dir)


def test_counts_and_ranges(face):
    assert face.neutral.shape == (468, 3) and face.neutral.dtype == np.float32
    assert face.faces.shape == (898, 3) and face.faces.dtype == np.int32
    assert face.faces.min() == 0 and face.faces.max() == 467
    assert face.uv.shape == (468, 2) and face.face_uv_idx.shape == (898, 3)
    assert np.all((face.uv >= 0) & (face.uv <= 1))


def test_one_component(face):
    e = np.concatenate([face.faces[:, [0, 1]], face.faces[:, [1, 2]], face.faces[:, [2, 0]]])
    graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(468, 468))
    n, _ = connected_components(graph, directed=False)
    assert n == 1


def test_matches_raw_obj(face, data_dir):
    mesh = trimesh.load(
        data_dir / "mediapipe/raw_canonical_face_model.obj", process=False, maintain_order=True
    )
    assert mesh.vertices.shape == (468, 3)
    np.testing.assert_allclose(face.neutral, mesh.vertices, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(face.faces, mesh.faces)
