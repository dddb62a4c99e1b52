"""One voice: every library warning is a ``CanrigWarning`` pointing at the user's line.

Each case calls a public function from this file; the warning's ``filename`` must be this
file (not a module inside ``canrig_jax``), however deep in the package the check sits.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from canrig_jax import CanrigWarning
from canrig_jax.data import (
    capture_from_weights,
    read_livelink_csv,
    write_livelink_csv,
)
from canrig_jax.inverse import prepare
from canrig_jax.rig import BlendshapeRig


def _caught(call):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = call()
    return result, caught


def _assert_at_this_file(caught, text):
    ours = [w for w in caught if text in str(w.message)]
    assert ours, [str(w.message) for w in caught]
    for w in ours:
        assert issubclass(w.category, CanrigWarning), w.category
        assert w.filename == __file__, (w.filename, str(w.message))


def test_dropped_frames_in_a_take(tmp_path):
    capture = capture_from_weights(np.zeros((5, 1), np.float32), ["JawOpen"], fps=60)
    frames = capture.frame_number.copy()
    frames[3:] += 4  # 4 frames lost before the 4th row
    write_livelink_csv(tmp_path / "t.csv", dataclasses.replace(capture, frame_number=frames))
    take, caught = _caught(lambda: read_livelink_csv(tmp_path / "t.csv", fps=60))
    _assert_at_this_file(caught, "4 frames dropped")
    assert take.n_frames == 5


def test_channels_a_rig_does_not_read(tmp_path):
    """``weights_for`` warns through ``retarget_weights``: still this file's line."""
    capture = capture_from_weights(np.ones((2, 2), np.float32), ["JawOpen", "TongueOut"])
    weights, caught = _caught(lambda: capture.weights_for(["jawOpen"]))
    _assert_at_this_file(caught, "TongueOut")
    np.testing.assert_array_equal(weights, np.ones((2, 1)))


def test_a_take_too_short_to_show_its_frame_rate(tmp_path):
    """Two calls deep inside ``read_livelink_csv``: still this file's line."""
    capture = capture_from_weights(np.zeros((5, 1), np.float32), ["JawOpen"], fps=60)
    write_livelink_csv(tmp_path / "t.csv", capture)
    take, caught = _caught(lambda: read_livelink_csv(tmp_path / "t.csv"))
    _assert_at_this_file(caught, "never crosses a second")
    assert take.fps == 60.0


def test_dropped_zero_shapes():
    neutral = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    deltas = np.zeros((2, 3, 3), np.float32)
    deltas[0, 0, 2] = 1.0  # shape b is all zero
    rig = BlendshapeRig(neutral, deltas, (), ("a", "b"), np.array([[0, 1, 2]]))
    problem, caught = _caught(lambda: prepare(rig, drop_zero_shapes=True))
    _assert_at_this_file(caught, "dropping blendshapes ['b']")
    assert problem.rig.names == ("a",)
