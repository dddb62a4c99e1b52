"""``triangulate_quads`` against the triangulations the real assets ship with."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import data_file
from canrig_jax.mesh import triangulate_quads


@pytest.mark.parametrize(
    "path", ["ict-facekit/expressions.npz", "makehuman/hm08_face.npz"], ids=["ict", "makehuman"]
)
def test_matches_the_shipped_fan_split(data_dir, path):
    with np.load(data_file(path, data_dir), allow_pickle=False) as z:
        polys, faces = z["polys"], z["faces"]
    np.testing.assert_array_equal(triangulate_quads(polys), faces)


@pytest.mark.bad_input
def test_triangles_padded_by_repetition_or_minus_one_and_bad_input():
    polys = np.array([[0, 1, 2, 3], [4, 5, 6, 6], [7, 8, 9, -1]])
    expected = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]]
    np.testing.assert_array_equal(triangulate_quads(polys), expected)
    # every quad's two triangles cover it: same area as the quad for a unit square
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tris = square[triangulate_quads(polys[:1])]
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    assert area.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="polys"):
        triangulate_quads(polys[:, :3])
    with pytest.raises(ValueError, match="polys"):
        triangulate_quads(polys.astype(float))
    with pytest.raises(ValueError, match="polys"):
        triangulate_quads(np.array([[0, 0, 1, 2]]))
