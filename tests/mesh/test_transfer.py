"""Deformation transfer (Sumner & Popović 2004) on ICT heads."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import FACE, ict_identity, load_ict
from canrig_jax.mesh import (
    closest_point_correspondence,
    connected_components,
    decimate,
    similarity_transform,
)
from canrig_jax.mesh._transfer import identity_correspondence
from canrig_jax.rig import BlendshapeRig, Corrective, deformation_transfer

MM = 10.0


@pytest.fixture(scope="module")
def face(data_dir):
    return load_ict(data_dir, parts=FACE)


@pytest.fixture(scope="module")
def face_rig(face):
    return BlendshapeRig(face.neutral, face.deltas, (), face.names, face.faces)


def _rotation(seed):
    q = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))[0]
    return q * np.sign(np.linalg.det(q))


def test_similarity_transform_recovers_a_known_one(face):
    points = face.neutral[face.landmarks].astype(np.float64)
    rotation = _rotation(1)
    scale, found_rotation, shift = similarity_transform(points, 1.3 * points @ rotation.T + 2.0)
    assert abs(scale - 1.3) < 1e-9
    np.testing.assert_allclose(found_rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(shift, 2.0, atol=1e-8)


def test_transfer_onto_the_source_itself_reproduces_the_rig(face, face_rig):
    out = deformation_transfer(
        face_rig, face.neutral, identity_correspondence(face.faces, face.n_vertices)
    )
    assert out.names == face_rig.names and out.correctives == ()
    error_mm = np.abs(np.asarray(out.deltas) - face.deltas).max() * MM
    assert error_mm < 1e-3


def test_transfer_commutes_with_a_similarity(face, face_rig):
    """Closed form: onto s R x + t the deltas are s R d (the gradients are conjugated by R,
    and stretch-free scaling leaves them unchanged)."""
    rotation = _rotation(2)
    target = 0.8 * face.neutral.astype(np.float64) @ rotation.T + np.array([3.0, -1.0, 2.0])
    out = deformation_transfer(
        face_rig, target, identity_correspondence(face.faces, face.n_vertices)
    )
    expected = 0.8 * face.deltas.astype(np.float64) @ rotation.T
    assert np.abs(np.asarray(out.deltas) - expected).max() * MM < 1e-3


def test_transfer_to_an_identity_stays_close_to_the_identity_expressions(data_dir, face, face_rig):
    """ICT identities share the generic expression deltas, so they are a reference; the
    transfer through deformation gradients differs from them by a fraction of a millimetre."""
    target = ict_identity(np.random.default_rng(0).standard_normal(100), data_dir, model=face)
    out = deformation_transfer(
        face_rig, target, identity_correspondence(face.faces, face.n_vertices)
    )
    error_mm = np.linalg.norm(np.asarray(out.deltas) - face.deltas, axis=-1) * MM
    magnitude_mm = np.linalg.norm(face.deltas, axis=-1) * MM
    assert error_mm.mean() < 0.1 * magnitude_mm.mean()
    assert np.percentile(error_mm, 95) < 0.5


def test_transfer_across_topology_matches_the_carried_ground_truth(data_dir, face, face_rig):
    """Generic face -> an identity's face decimated to 3,000 vertices, correspondence from the
    68 landmarks and closest points; ground truth: the identity's expressions carried by the
    decimation's surface map."""
    target = ict_identity(np.random.default_rng(1).standard_normal(100), data_dir, model=face)
    coarse = decimate(target, face.faces, 3000)
    landmarks = coarse.nearest_vertices(target[face.landmarks])
    correspondence = closest_point_correspondence(
        face.neutral, face.faces, coarse.vertices, coarse.faces, face.landmarks, landmarks
    )
    distance = correspondence.vertex_map.distance  # cm, after the TPS warp
    assert np.median(distance) < 0.1 and np.percentile(distance, 99) < 1.0  # measured ~0.05, ~0.6
    out = deformation_transfer(face_rig, coarse.vertices, correspondence)
    truth = coarse.map.carry(face.deltas)
    error_mm = np.linalg.norm(np.asarray(out.deltas) - truth, axis=-1) * MM
    assert out.deltas.shape == truth.shape
    assert error_mm.mean() < 0.2 and np.percentile(error_mm, 95) < 1.0


@pytest.mark.bad_input
def test_bad_input(face, face_rig):
    correspondence = identity_correspondence(face.faces, face.n_vertices)
    with pytest.raises(ValueError, match="^source_rig:"):
        deformation_transfer(BlendshapeRig(face.neutral, face.deltas), face.neutral, correspondence)
    with pytest.raises(ValueError, match="^target_neutral:"):
        deformation_transfer(face_rig, face.neutral[:-1], correspondence)
    with pytest.raises(ValueError, match="^target_neutral:"):
        deformation_transfer(face_rig, np.full_like(face.neutral, np.nan), correspondence)
    with pytest.raises(ValueError, match="^screening:"):
        deformation_transfer(face_rig, face.neutral, correspondence, screening=0.0)
    with pytest.raises(ValueError, match="^source_landmarks, target_landmarks:"):
        closest_point_correspondence(
            face.neutral, face.faces, face.neutral, face.faces, face.landmarks, face.landmarks[:5]
        )
    corrected = BlendshapeRig(
        face.neutral,
        face.deltas[:2],
        (Corrective.from_dense([[0, 1]], np.ones((1, face.n_vertices, 3), np.float32)),),
        face.names[:2],
        face.faces,
    )
    with pytest.warns(UserWarning, match="correctives are not transferred"):
        deformation_transfer(corrected, face.neutral, correspondence)


STATIC_CM = 1e-3  # the evaluation's static threshold, 0.01 mm


@pytest.fixture(scope="module")
def remeshed_identity(data_dir, face):
    """An identity's face decimated to 2,000 vertices, its correspondence to the generic face
    (landmarks + closest points) and its ground truth (the identity's expressions carried by
    the decimation's surface map)."""
    target = ict_identity(np.random.default_rng(3).standard_normal(100), data_dir, model=face)
    coarse = decimate(target, face.faces, 2000)
    landmarks = coarse.nearest_vertices(target[face.landmarks])
    correspondence = closest_point_correspondence(
        face.neutral, face.faces, coarse.vertices, coarse.faces, face.landmarks, landmarks
    )
    return coarse, correspondence, coarse.map.carry(face.deltas)


def test_anchored_transfer_holds_what_the_source_leaves_still(face, face_rig, remeshed_identity):
    """Anchored vertices are exactly zero; the rest move; where the ground truth is static the
    anchored error is far below plain DT's, and the error overall is no larger."""
    coarse, correspondence, truth = remeshed_identity
    plain = np.asarray(deformation_transfer(face_rig, coarse.vertices, correspondence).deltas)
    anchored = np.asarray(
        deformation_transfer(
            face_rig, coarse.vertices, correspondence, static_below=STATIC_CM
        ).deltas
    )
    carried = np.linalg.norm(correspondence.vertex_map.carry(face.deltas), axis=-1)
    # the anchors are scaled by the carried-neutral similarity (~1 here): margins of 2x
    still, moving = carried < 0.5 * STATIC_CM, carried > 2 * STATIC_CM
    assert still.mean() > 0.3 and moving.mean() > 0.1
    assert np.all(anchored[still] == 0.0)
    assert np.all(np.linalg.norm(anchored[moving], axis=-1) > 0)
    error = {
        name: np.linalg.norm(out - truth, axis=-1) * MM
        for name, out in (("plain", plain), ("anchored", anchored))
    }
    static = np.linalg.norm(truth, axis=-1) < STATIC_CM
    assert error["anchored"][static].mean() < 0.5 * error["plain"][static].mean()
    assert error["anchored"].mean() <= error["plain"].mean()


def test_anchored_transfer_off_is_plain_and_onto_itself_reproduces(face, face_rig):
    correspondence = identity_correspondence(face.faces, face.n_vertices)
    rig = BlendshapeRig(face.neutral, face.deltas[:6], (), face.names[:6], face.faces)
    plain = np.asarray(deformation_transfer(rig, face.neutral, correspondence).deltas)
    none = deformation_transfer(rig, face.neutral, correspondence, static_below=None)
    np.testing.assert_array_equal(np.asarray(none.deltas), plain)
    anchored = np.asarray(
        deformation_transfer(rig, face.neutral, correspondence, static_below=STATIC_CM).deltas
    )
    # exact but for the anchored deltas, each shorter than the threshold
    assert np.linalg.norm(anchored - face.deltas[:6], axis=-1).max() <= STATIC_CM + 1e-6
    assert np.all(anchored[np.linalg.norm(face.deltas[:6], axis=-1) < 0.5 * STATIC_CM] == 0)


@pytest.mark.bad_input
@pytest.mark.parametrize("bad", [-1e-3, np.nan, np.inf, "0.01"])
def test_anchored_transfer_bad_threshold(face, face_rig, bad):
    correspondence = identity_correspondence(face.faces, face.n_vertices)
    with pytest.raises(ValueError, match="^static_below:"):
        deformation_transfer(face_rig, face.neutral, correspondence, static_below=bad)


@pytest.fixture(scope="module")
def mouth_and_eye(data_dir):
    """ICT's gums and tongue, teeth and left eyeball: separate parts, of which some move as a
    whole (the lower teeth with the jaw), some never (the eyeball) and one partly (the gums
    and tongue: the lower gums and the tongue follow the jaw, the upper gums stay)."""
    return load_ict(data_dir, parts=("Gums and tongue", "Teeth", "Eyeball left"))


def test_per_part_anchoring_holds_whole_parts_only(data_dir, mouth_and_eye):
    """Per-part anchoring on real ICT parts (an identity's shape): a part whose source is still
    in an expression is held at exactly zero; a part that moves anywhere is never held (no
    vertex of it exactly zero), although per-vertex anchoring holds part of it; all labels -1
    is per-vertex anchoring, bit for bit."""
    model = mouth_and_eye
    chosen = [model.names.index(n) for n in ("jawOpen", "jawLeft", "browDown_L", "eyeBlink_L")]
    rig = BlendshapeRig(
        model.neutral, model.deltas[chosen], (), [model.names[i] for i in chosen], model.faces
    )
    target = ict_identity(np.random.default_rng(5).standard_normal(100), data_dir, model=model)
    correspondence = identity_correspondence(model.faces, model.n_vertices)
    labels = connected_components(model.faces, model.n_vertices)
    per_part = np.asarray(
        deformation_transfer(
            rig, target, correspondence, static_below=STATIC_CM, static_parts=labels
        ).deltas
    )
    per_vertex = np.asarray(
        deformation_transfer(rig, target, correspondence, static_below=STATIC_CM).deltas
    )
    # the carried-neutral similarity scales the threshold (~1 here): a 2x margin either way
    scale, _, _ = similarity_transform(model.neutral, target)
    assert 0.9 < scale < 1.1
    motion = np.linalg.norm(model.deltas[chosen], axis=-1)  # (4, V)
    held = np.all(per_part == 0.0, axis=-1)
    counts = {"still": 0, "moving": 0, "split_by_vertex": 0}
    for part in np.unique(labels):
        members = labels == part
        for k in range(len(chosen)):
            peak = motion[k, members].max()
            if peak < 0.5 * STATIC_CM:
                assert held[k, members].all()
                counts["still"] += 1
            elif peak > 2 * STATIC_CM:
                assert not held[k, members].any(), (rig.names[k], int(part))
                counts["moving"] += 1
                vertex_held = np.all(per_vertex[k, members] == 0.0, axis=-1)
                counts["split_by_vertex"] += int(vertex_held.any())
    # every case occurs: still parts, moving parts, moving parts per-vertex anchoring splits
    assert counts["still"] > 10 and counts["moving"] > 10 and counts["split_by_vertex"] > 0
    everywhere = deformation_transfer(
        rig,
        target,
        correspondence,
        static_below=STATIC_CM,
        static_parts=np.full(model.n_vertices, -1),
    )
    np.testing.assert_array_equal(np.asarray(everywhere.deltas), per_vertex)


@pytest.mark.bad_input
@pytest.mark.parametrize(
    ("labels", "threshold"),
    [
        (np.zeros(3, np.int64), STATIC_CM),  # wrong length
        ("float", STATIC_CM),
        ("minus_two", STATIC_CM),
        ("zeros", None),  # per-part anchoring without a threshold
    ],
)
def test_per_part_anchoring_bad_labels(face, face_rig, labels, threshold):
    correspondence = identity_correspondence(face.faces, face.n_vertices)
    if isinstance(labels, str):
        labels = {
            "float": np.zeros(face.n_vertices),
            "minus_two": np.full(face.n_vertices, -2),
            "zeros": np.zeros(face.n_vertices, np.int64),
        }[labels]
    rig = BlendshapeRig(face.neutral, face.deltas[:2], (), face.names[:2], face.faces)
    with pytest.raises(ValueError, match="^static_parts:"):
        deformation_transfer(
            rig, face.neutral, correspondence, static_below=threshold, static_parts=labels
        )


def _two_sheets(gap: float, drop: float):
    """Two parallel 6 x 6 grids facing each other (an upper and a lower "lip", y = +-gap/2),
    as one mesh; the upper sheet lowered by ``drop``. (vertices, faces, (V,) side 0/1)."""
    x, z = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6))
    grid = np.c_[x.ravel(), np.zeros(36), z.ravel()]
    quads = [(i * 6 + j, i * 6 + j + 1, (i + 1) * 6 + j) for i in range(5) for j in range(5)]
    quads += [
        (i * 6 + j + 1, (i + 1) * 6 + j + 1, (i + 1) * 6 + j) for i in range(5) for j in range(5)
    ]
    tri = np.array(quads)
    upper = grid + [0, gap / 2 - drop, 0]
    lower = grid - [0, gap / 2, 0]
    return np.r_[upper, lower], np.r_[tri, tri + 36], np.repeat([0, 1], 36)


def test_sides_keep_closest_points_from_crossing_a_slit():
    source, faces, side = _two_sheets(0.2, 0.0)
    target, _, _ = _two_sheets(0.2, 0.15)  # its upper sheet nearer the source's lower one
    landmarks = np.array([36, 41, 66, 71])  # on the lower sheet: the similarity is the identity
    kwargs = dict(nonrigid=False, match_components=False)
    plain = closest_point_correspondence(
        source, faces, target, faces, landmarks, landmarks, **kwargs
    )
    sided = closest_point_correspondence(
        source, faces, target, faces, landmarks, landmarks, source_sides=side, target_sides=side,
        **kwargs,
    )  # fmt: skip
    landed = lambda c: side[faces[c.vertex_map.triangle]].max(axis=1)  # noqa: E731
    assert (landed(plain)[:36] == 1).all()  # the premise: unsided, the upper sheet crosses
    np.testing.assert_array_equal(landed(sided), side)
    samples_landed = side[faces[sided.source_triangle]].max(axis=2)  # (T, 4) each sample's
    assert (samples_landed == side[faces][:, :1]).all()
    # a point of side -1 may land anywhere: all -1 is the plain correspondence
    free = closest_point_correspondence(
        source, faces, target, faces, landmarks, landmarks,
        source_sides=np.full(72, -1), target_sides=np.full(72, -1), **kwargs,
    )  # fmt: skip
    np.testing.assert_array_equal(free.vertex_map.triangle, plain.vertex_map.triangle)
    with pytest.raises(ValueError, match="source_sides, target_sides"):
        closest_point_correspondence(
            source, faces, target, faces, landmarks, landmarks, source_sides=side
        )
    with pytest.raises((TypeError, ValueError), match="target_sides"):
        closest_point_correspondence(
            source, faces, target, faces, landmarks, landmarks, source_sides=side,
            target_sides=side[:10],
        )  # fmt: skip


def test_source_gradients_once_per_source_triangle_are_those_of_every_sample(data_dir, face):
    # the sampled source triangles of a real correspondence repeat (four samples per target
    # triangle, neighbours sharing source triangles): computed once per distinct triangle and
    # gathered, the deformation gradients are those computed sample by sample
    from canrig_jax.mesh._deformation_gradient import triangle_frames
    from canrig_jax.mesh._transfer import _source_gradients, _source_samples

    target = ict_identity(np.random.default_rng(3).standard_normal(100), data_dir, model=face)
    coarse = decimate(target, face.faces, 2000)
    landmarks = coarse.nearest_vertices(target[face.landmarks])
    correspondence = closest_point_correspondence(
        face.neutral, face.faces, coarse.vertices, coarse.faces, face.landmarks, landmarks
    )
    neutral = np.asarray(face.neutral, np.float64)
    triangle = correspondence.source_triangle
    samples = _source_samples(neutral, face.faces, triangle, 1e-10)
    assert len(samples.faces) < triangle.size  # shared source triangles
    posed = neutral + np.asarray(face.deltas[:4], np.float64)
    gradient = _source_gradients(posed, samples, 1e-10)
    # sample by sample
    faces = face.faces[triangle.ravel()]
    rest, rest_area = triangle_frames(neutral, faces)
    frame, area = triangle_frames(posed, faces)
    each = frame @ np.linalg.inv(np.where(rest_area[:, None, None] >= 1e-10, rest, np.eye(3)))
    each = np.where(((rest_area >= 1e-10) & (area >= 1e-10))[..., None, None], each, np.eye(3))
    weight = np.where(rest_area >= 1e-10, rest_area, 0.0).reshape(triangle.shape)
    weight /= weight.sum(axis=1, keepdims=True)
    want = np.einsum("btsij,ts->btij", each.reshape(4, *triangle.shape, 3, 3), weight)
    np.testing.assert_array_equal(gradient, want)
