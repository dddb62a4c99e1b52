"""The rigger's checks: an artist's rig passes every hard check, and each check fails on the
rig broken in the one way it looks for (the artist's shapes edited: the blink removed, the
jaw turned upwards, an eyeball squashed, a shape crumpled)."""

import numpy as np
import pytest

from canrig_jax import autorig
from canrig_jax.autorig._landmarks import skin_of
from canrig_jax.autorig._rig_checks import _head
from canrig_jax.mesh import flipped_triangles
from canrig_jax.rig import BlendshapeRig, evaluate_batch


@pytest.fixture(scope="module")
def artist(data_dir):
    """Rocketbox Male_Adult_08's own ARKit rig (validation head), cm, +y up facing +z."""
    h = autorig.load_rocketbox_head("Male_Adult_08", data_dir)
    return BlendshapeRig(h.vertices, h.deltas, (), tuple(h.names), h.faces, "cm")


@pytest.fixture(scope="module")
def artist_checks(artist):
    return autorig.check_rig(artist, n_random=16)


def _edited(rig: BlendshapeRig, name: str, edit) -> BlendshapeRig:
    deltas = np.array(rig.deltas)
    k = rig.names.index(name)
    deltas[k] = edit(deltas[k], np.asarray(rig.neutral))
    return BlendshapeRig(rig.neutral, deltas, (), rig.names, rig.faces, rig.units)


def test_the_artists_rig_passes_every_hard_check(artist_checks):
    assert artist_checks.ok, artist_checks.table()
    assert artist_checks.failed == ()
    assert [c.name for c in artist_checks.checks] == list(autorig.CHECK_LIMITS)


def test_a_blink_that_does_not_move_leaves_the_eye_open(artist):
    result = autorig.check_rig(_edited(artist, "eyeBlinkLeft", lambda d, v: 0 * d), n_random=4)
    assert result["blink_closes"].value == pytest.approx(1.0)
    assert "blink_closes" in result.failed


def test_a_jaw_that_opens_upwards_fails_the_chin_check(artist):
    result = autorig.check_rig(_edited(artist, "jawOpen", lambda d, v: -d), n_random=4)
    assert result["chin_moves_down"].value < 0
    assert "chin_moves_down" in result.failed


def test_an_eyeball_squashed_by_a_look_is_not_rigid(artist, artist_checks):
    def squash(delta, neutral):
        eye = _head(artist, "+y", "+z").eyes[0]
        centre = neutral[eye].mean(axis=0)
        out = delta.copy()
        out[eye] += (neutral[eye] - centre) * np.array([0.0, -0.4, 0.0])  # flattened 40 %
        return out

    result = autorig.check_rig(_edited(artist, "eyeLookUpLeft", squash), n_random=4)
    assert artist_checks["eyes_rigid"].value < 0.01
    assert result["eyes_rigid"].value > autorig.CHECK_LIMITS["eyes_rigid"][0]


def test_flipped_triangles_are_counted_per_frame_against_an_independent_count(artist):
    rng = np.random.default_rng(0)
    crumpled = _edited(
        artist, "mouthSmileLeft", lambda d, v: d + rng.normal(0, 0.6, d.shape) * (np.abs(d) > 0)
    )
    result = autorig.check_rig(crumpled, n_random=8)
    frames = np.asarray(evaluate_batch(crumpled, result.poses))
    skin = skin_of(np.asarray(crumpled.neutral), np.asarray(crumpled.faces))
    mask = skin[np.asarray(crumpled.faces)].all(axis=1)
    expected = flipped_triangles(frames, crumpled.neutral, crumpled.faces, mask=mask).sum(1)
    np.testing.assert_array_equal(result.flips, expected)
    assert result["flipped_triangles"].value == pytest.approx(expected.mean() / mask.sum())


def test_the_take_drives_the_geometry_checks(artist, data_dir):
    from canrig_jax.data import load_livelinkface

    poses = load_livelinkface(data_dir).weights_for(artist.names, missing="zero")[:30]
    result = autorig.check_rig(artist, poses)
    assert result.source == "take" and result.flips.shape == (30,)
    np.testing.assert_array_equal(result.poses, poses)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda r: BlendshapeRig(r.neutral, r.deltas, (), r.names, None, "cm"), "faces"),
        (
            lambda r: BlendshapeRig(
                r.neutral, r.deltas, (), tuple(f"s{i}" for i in range(len(r.names))), r.faces
            ),
            "ARKit",
        ),
    ],
)
def test_a_rig_that_cannot_be_checked_is_named(artist, edit, message):
    with pytest.raises(ValueError, match=message):
        autorig.check_rig(edit(artist))


def test_weights_of_another_rig_or_nan_are_named(artist):
    with pytest.raises(ValueError, match=r"poses: expected \(T, 52\)"):
        autorig.check_rig(artist, np.zeros((5, 51)))
    with pytest.raises(ValueError, match="poses: contains NaN"):
        autorig.check_rig(artist, np.full((5, 52), np.nan))


def test_close_blinks_restores_a_blink_that_stops_short(artist, artist_checks):
    """The artist's blink at half its amplitude leaves the eye open; ``close_blinks`` scales
    it back until the lid covers the eyeball (and leaves the artist's own at gain 1)."""
    from canrig_jax.autorig._blink_fit import close_blinks

    half = _edited(artist, "eyeBlinkLeft", lambda d, v: 0.5 * d)
    assert autorig.check_rig(half, n_random=4)["blink_closes"].value > 0.25
    fixed, gains = close_blinks(half)
    assert gains["eyeBlinkRight"] == 1.0  # the artist's own: not pushed through the other lid
    assert 1.5 <= gains["eyeBlinkLeft"] <= 2.5
    k = artist.names.index("eyeBlinkLeft")
    np.testing.assert_allclose(
        np.asarray(fixed.deltas[k]), gains["eyeBlinkLeft"] * np.asarray(half.deltas[k]), rtol=1e-6
    )
    closed = autorig.check_rig(fixed, n_random=4)["blink_closes"].value
    assert closed <= artist_checks["blink_closes"].value + 1e-9  # as closed as the artist's
    _, kept = close_blinks(half, keep=("eyeBlinkLeft",))
    assert "eyeBlinkLeft" not in kept
