"""The sides of a face's slits (``autorig._slits``)."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.autorig import ict_pose_source
from canrig_jax.autorig._slits import SLITS, slit_sides


@pytest.fixture(scope="module")
def ict_head(data_dir):
    return ict_pose_source(data_dir, progress=False).head


def test_the_lips_and_lids_of_the_ict_face_fall_on_their_own_sides(ict_head):
    h = ict_head
    sides = slit_sides(h.neutral, h.faces, h.landmarks)
    lm = np.asarray(h.landmarks)
    # inner lip landmarks: 61-63 on the upper lip, 65-67 on the lower (not used as seeds)
    assert (sides[lm[61:64]] == 0).all() and (sides[lm[65:68]] == 1).all()
    for i, (upper, lower, _) in enumerate(SLITS.values()):
        assert (sides[lm[list(upper)]] == 2 * i).all()
        assert (sides[lm[list(lower)]] == 2 * i + 1).all()
    # the forehead and the back of the head are far from every slit
    assert sides[np.argmax(h.neutral[:, 1])] == -1 and sides[np.argmin(h.neutral[:, 2])] == -1
    # the two sides of the mouth are apart along the surface: no vertex of the upper lip's
    # side shares a triangle with the lower lip's except around the corners and inside
    corner = sides[h.faces]
    mixed = np.flatnonzero((corner == 0).any(1) & (corner == 1).any(1))
    centre = h.neutral[h.faces[mixed]].mean(1)
    front = h.neutral[lm[[62, 66]]].mean(0)
    assert np.all(np.linalg.norm(centre - front, axis=1) > 0.5)  # cm: none at the lips' front


def test_a_slit_the_mesh_does_not_part_is_left_unlabelled(ict_head):
    h = ict_head
    lm = np.array(h.landmarks)
    lm[[56, 57, 58]] = lm[[50, 51, 52]]  # both sides of the mouth on the same vertices
    sides = slit_sides(h.neutral, h.faces, lm)
    assert not np.isin(sides, (0, 1)).any()
    assert np.isin(sides, (2, 3, 4, 5)).any()  # the eyes are labelled still
    with pytest.raises(ValueError, match="landmarks"):
        slit_sides(h.neutral, h.faces, lm[:60])
