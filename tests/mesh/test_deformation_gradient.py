"""The deformation-gradient blend on the real ICT face: exact targets, rigid equivariance,
genuine nonlinearity, and the linear fallback of half-turn triangles."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.mesh import DeformationGradientBlend
from canrig_jax.mesh._deformation_gradient import triangle_edges
from canrig_jax.rig import BlendshapeRig, deformation_gradient_blend

SHAPES = ("jawOpen", "mouthClose", "mouthSmile_L", "mouthFunnel", "eyeBlink_L", "browDown_L")


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues' rotation matrix about ``axis``."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.deg2rad(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _max_vertex_distance(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1).max())


@pytest.fixture(scope="module")
def face(ict_face):
    """Float64 neutral (V, 3), deltas (K, V, 3) of SHAPES and faces of the ICT face part."""
    index = ict_face.index(SHAPES)
    return (
        np.asarray(ict_face.neutral, np.float64),
        np.asarray(ict_face.deltas, np.float64)[index],
        np.asarray(ict_face.faces),
    )


@pytest.fixture(scope="module")
def blend(face):
    return DeformationGradientBlend(*face)


def test_every_single_target_is_reproduced(face, blend):
    """At w = e_i the blended edges are the target's, so the target comes back (< 1e-3 mm)."""
    neutral, deltas, _ = face
    out = blend(np.eye(len(SHAPES)))
    assert out.shape == (len(SHAPES), neutral.shape[0], 3) and out.dtype == np.float64
    for i, name in enumerate(SHAPES):
        error = _max_vertex_distance(out[i], neutral + deltas[i])
        assert error < 1e-4, f"{name}: target missed by {error:.2e} cm"


def test_every_ict_expression_is_reproduced(ict_face, ict_face_blend):
    """All 53 ICT targets at once (the blend of the whole expression set)."""
    out = ict_face_blend(np.eye(ict_face.n_blendshapes))
    expected = np.asarray(ict_face.neutral, np.float64) + np.asarray(ict_face.deltas, np.float64)
    errors = np.linalg.norm(out - expected, axis=-1).max(axis=1)
    assert errors.max() < 1e-4, dict(zip(ict_face.names, errors.round(6), strict=True))


def test_rig_level_entry_point_matches_the_blend(ict_face, face, blend):
    """``deformation_gradient_blend(rig, w)`` is the prefactorised blend of the rig's mesh."""
    neutral, deltas, faces = face
    rig = BlendshapeRig(neutral.astype(np.float32), deltas.astype(np.float32), (), SHAPES, faces)
    poses = np.array([[0.2, 0.9, 0.4, 0.0, 0.1, 0.5], [1.0, 0.0, 0.0, 0.7, 0.0, 0.0]])
    np.testing.assert_allclose(deformation_gradient_blend(rig, poses), blend(poses), atol=1e-5)
    single = deformation_gradient_blend(rig, poses[1])
    np.testing.assert_allclose(single, blend(poses[1]), atol=1e-5)
    with pytest.raises(ValueError, match="faces"):
        deformation_gradient_blend(BlendshapeRig(rig.neutral, rig.deltas), poses)


def test_zero_weights_give_the_neutral(face, blend):
    neutral = face[0]
    out = blend(np.zeros(len(SHAPES)))
    assert out.shape == neutral.shape
    assert _max_vertex_distance(out, neutral) < 1e-5


def test_rigid_motion_equivariance(face, blend):
    """Rotating (and translating) the neutral and every target by one rigid motion rotates
    the blend at a mixed pose: the blend has no preferred frame."""
    neutral, deltas, faces = face
    rotation = _rotation([0.3, -1.0, 0.4], 63.0)
    shift = np.array([5.0, -2.0, 3.0])
    moved = DeformationGradientBlend(neutral @ rotation.T + shift, deltas @ rotation.T, faces)
    poses = np.array([[0.8, 0.6, 0.5, 0.0, 0.7, 0.3], [0.3, 0.9, 0.0, 0.6, 0.2, 0.9]])
    expected = blend(poses) @ rotation.T + shift
    assert _max_vertex_distance(moved(poses), expected) < 1e-4
    assert moved.fallback_counts == blend.fallback_counts


def test_jaw_open_with_mouth_close_is_far_from_linear(face, blend):
    """The blend is genuinely nonlinear: jawOpen + mouthClose (lips sealed on an open jaw)
    departs from the linear sum by more than 1 mm, while a lone target does not."""
    neutral, deltas, _ = face
    pose = np.zeros(len(SHAPES))
    pose[[SHAPES.index("jawOpen"), SHAPES.index("mouthClose")]] = 1.0
    linear = neutral + np.tensordot(pose, deltas, axes=1)
    assert _max_vertex_distance(blend(pose), linear) > 0.1


def test_half_weight_rotation_is_not_a_shrinking_average(face, blend):
    """Halfway to jawOpen the jaw rotates rather than interpolating chords: the blended mesh
    differs from the linear one by tenths of a millimetre at least."""
    neutral, deltas, _ = face
    pose = np.zeros(len(SHAPES))
    pose[SHAPES.index("jawOpen")] = 0.5
    linear = neutral + np.tensordot(pose, deltas, axes=1)
    assert _max_vertex_distance(blend(pose), linear) > 0.01


def test_bad_weights_raise(blend):
    k = len(SHAPES)
    for shape in [(k + 1,), (2, k - 1), (2, 2, k)]:
        with pytest.raises(ValueError, match="weights"):
            blend(np.zeros(shape))
    bad = np.zeros(k)
    bad[2] = np.nan
    with pytest.raises(ValueError, match="weights"):
        blend(bad)


# --- the linear fallback ----------------------------------------------------------------------


def _two_triangles(first_degrees: float, second_degrees: float):
    """Two disjoint triangles in the z = 0 plane; the single target turns the first by
    ``first_degrees`` and the second by ``second_degrees`` in-plane about their centroids."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.2, 0.9, 0.0]])
    neutral = np.concatenate([tri, tri + [3.0, 0.0, 0.0]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    target = neutral.copy()
    for rows, degrees in [(slice(0, 3), first_degrees), (slice(3, 6), second_degrees)]:
        centre = neutral[rows].mean(axis=0)
        target[rows] = (neutral[rows] - centre) @ _rotation([0, 0, 1], degrees).T + centre
    return neutral, (target - neutral)[None], faces


def test_half_turn_triangle_falls_back_to_linear_edges():
    neutral, deltas, faces = _two_triangles(178.0, 90.0)
    blend = DeformationGradientBlend(neutral, deltas, faces)
    counts = blend.fallback_counts
    assert (counts.near_half_turn, counts.total, counts.degenerate, counts.inverted) == (1, 1, 0, 0)
    assert blend.fallback.tolist() == [True, False]

    w = 0.5
    out = blend(np.array([w]))
    linear = neutral + w * deltas[0]
    # The half-turn triangle is blended linearly: its own edges agree with the linear mesh,
    # so it comes out exactly as the linear blend (its chords shrink to ~cos(89 deg)).
    np.testing.assert_allclose(out[:3], linear[:3], atol=1e-6)
    # The quarter-turn triangle rotates by 45 degrees and keeps its edge lengths, where the
    # linear blend would shrink them to cos(45 deg) = 0.71.
    rest_lengths = np.linalg.norm(triangle_edges(neutral, faces)[1], axis=0)
    blended_lengths = np.linalg.norm(triangle_edges(out, faces)[1], axis=0)
    linear_lengths = np.linalg.norm(triangle_edges(linear, faces)[1], axis=0)
    np.testing.assert_allclose(linear_lengths / rest_lengths, np.cos(np.pi / 4), rtol=1e-6)
    assert np.all(blended_lengths / rest_lengths > 0.95)


def test_small_turns_do_not_fall_back():
    neutral, deltas, faces = _two_triangles(150.0, 30.0)
    blend = DeformationGradientBlend(neutral, deltas, faces)
    assert blend.fallback_counts.total == 0
    # 150 degrees is blended as a rotation: halfway is 75 degrees with full-length edges.
    out = blend(np.array([0.5]))
    lengths = np.linalg.norm(triangle_edges(out, faces)[0], axis=0)
    rest = np.linalg.norm(triangle_edges(neutral, faces)[0], axis=0)
    assert np.all(lengths / rest > 0.95)


def test_ict_fallback_triangles_are_counted_and_blended_linearly(face, blend):
    """On the real face some triangles do fall back (near half turns); counting matches the
    mask, and a mesh whose only moving triangles all fall back is blended linearly."""
    neutral, deltas, faces = face
    counts = blend.fallback_counts
    assert counts.total == int(blend.fallback.sum()) > 0
    assert counts.total <= counts.degenerate + counts.inverted + counts.near_half_turn
    # Keep only the fallback triangles: their edges are linear, so the blend is linear.
    sub = DeformationGradientBlend(neutral, deltas, faces[blend.fallback])
    assert sub.fallback_counts.total == counts.total
    pose = np.array([0.7, 0.4, 0.0, 0.5, 0.9, 0.6])
    assert _max_vertex_distance(sub(pose), neutral + np.tensordot(pose, deltas, 1)) < 1e-5
