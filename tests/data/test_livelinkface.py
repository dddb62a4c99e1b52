"""Live Link Face capture loading and driving the ICT rig's channels."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import ARKIT_NAMES, load_ict, load_livelinkface


@pytest.fixture(scope="module")
def capture(data_dir):
    return load_livelinkface(data_dir)


def test_capture_contents(capture):
    assert capture.weights.shape == (180, 52) and capture.weights.dtype == np.float32
    assert capture.head_eye_rotations.shape == (180, 9)
    assert capture.rotation_names[0] == "HeadYaw" and len(capture.rotation_names) == 9
    assert capture.fps == 60.0 and capture.n_frames == 180
    steps = np.diff(capture.frame_number)
    assert steps.min() == 1 and steps.max() == 8  # the README's one gap
    assert 0.0 <= capture.weights.min() and capture.weights.max() < 1.0


def test_weights_for_ict(capture, data_dir):
    names = load_ict(data_dir).names
    with pytest.warns(UserWarning, match="TongueOut"):
        w = capture.weights_for(names)
    assert w.shape == (180, 53) and w.dtype == np.float32
    assert w.min() >= 0.0 and w.max() <= 1.0
    src = {n: capture.weights[:, k] for k, n in enumerate(capture.names)}
    out = {n: w[:, k] for k, n in enumerate(names)}
    np.testing.assert_array_equal(out["eyeBlink_L"], src["EyeBlinkLeft"])
    np.testing.assert_array_equal(out["mouthSmile_R"], src["MouthSmileRight"])
    np.testing.assert_array_equal(out["jawOpen"], src["JawOpen"])
    np.testing.assert_array_equal(out["browInnerUp_L"], src["BrowInnerUp"])
    np.testing.assert_array_equal(out["browInnerUp_R"], src["BrowInnerUp"])
    np.testing.assert_array_equal(out["cheekPuff_R"], src["CheekPuff"])
    assert out["jawOpen"].max() > 0.05  # the capture does move the jaw


def test_weights_for_missing_channel(capture):
    with pytest.raises(ValueError, match="eyeBlink_X|target_names"):
        capture.weights_for(["eyeBlink_X"])
    w = capture.weights_for(list(ARKIT_NAMES))
    np.testing.assert_array_equal(w, capture.weights)
