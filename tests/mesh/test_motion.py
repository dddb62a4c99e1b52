"""Mesh quality under motion against closed forms: flips, edge stretch, crossings, rigid fit."""

import numpy as np
import pytest

from canrig_jax.mesh import edge_stretch, flipped_triangles, rigid_residual, self_intersections


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_flipped_triangles_counts_a_mirrored_triangle_only():
    neutral = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0], [2, 1, 0.0]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    moved = neutral.copy()
    moved[2, 1] = -1.0  # the first triangle folds through its edge (0, 1)
    frames = np.stack([neutral, moved, neutral @ _rotation(0).T])
    flips = flipped_triangles(frames, neutral, faces)
    np.testing.assert_array_equal(flips, [[False, False], [True, False], [False, False]])
    # a mask leaves the first triangle out
    assert not flipped_triangles(frames, neutral, faces, mask=np.array([False, True])).any()


def test_edge_stretch_of_a_uniform_scale_is_the_scale():
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=(4, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    frames = np.stack([neutral * 2.5, neutral @ _rotation(2).T + 1.0])
    stretch = edge_stretch(frames, neutral, faces)
    assert stretch.shape == (2, 5)  # five unique edges
    np.testing.assert_allclose(stretch[0], 2.5, rtol=1e-12)
    np.testing.assert_allclose(stretch[1], 1.0, rtol=1e-12)


def test_self_intersections_count_only_crossings_the_motion_made():
    # a triangle in z = 0 and a separate triangle above it, standing up; in frame 1 the second
    # one drops so that two of its edges pierce the first
    flat = [[-1, -1, 0], [2, -1, 0], [-1, 2, 0.0]]
    standing = [[0, 0, 0.5], [0.4, 0, 0.5], [0.2, 0.2, 1.5]]
    neutral = np.array(flat + standing)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    dropped = neutral.copy()
    dropped[3:, 2] -= 1.0
    counts = self_intersections(np.stack([neutral, dropped]), neutral, faces, near=10.0)
    np.testing.assert_array_equal(counts, [0, 2])
    # a crossing already in the neutral is not new
    np.testing.assert_array_equal(self_intersections(dropped[None], dropped, faces, near=10.0), [0])


def test_rigid_residual_is_zero_for_a_rigid_motion_and_known_for_a_scale():
    rng = np.random.default_rng(3)
    rest = rng.normal(size=(40, 3))
    moved = np.stack([rest @ _rotation(4).T + 2.0, rest * 1.2])
    residual = rigid_residual(rest, moved)
    assert residual[0] < 1e-12
    centred = rest - rest.mean(axis=0)
    expected = 0.2 * np.sqrt((centred**2).sum(axis=1).mean())  # scale 1.2: best rotation = I
    np.testing.assert_allclose(residual[1], expected, rtol=1e-9)


@pytest.mark.bad_input
def test_bad_frames_are_named():
    neutral = np.zeros((3, 3))
    with pytest.raises(ValueError, match="frames"):
        flipped_triangles(np.zeros((2, 4, 3)), neutral, np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="frames"):
        edge_stretch(np.full((1, 3, 3), np.nan), neutral, np.array([[0, 1, 2]]))
