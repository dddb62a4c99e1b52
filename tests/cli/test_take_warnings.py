"""Takes that are not what they seem: weights outside [0, 1] and channels a take lacks.

A Live Link cell of 7.5 must not animate a face at 7.5x without a word, and a take holding 3
of a rig's 8 channels must name the 5 it leaves at 0: both through the library reader,
``canrig animate`` and ``canrig retarget`` (a small synthetic rig, no data folder).
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from canrig_jax import CanrigWarning, run_command
from canrig_jax.data import capture_from_weights, read_livelink_csv, write_livelink_csv

ARKIT = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "mouthSmileRight",
         "browInnerUp", "cheekPuff", "mouthFunnel")  # fmt: skip
OUT_OF_RANGE = {(3, 0): 7.5, (7, 2): -0.25, (11, 5): 1.5}  # (frame, channel): value


@pytest.fixture(scope="module")
def files(tmp_path_factory, synthetic_rig):
    """rig.npz (8 ARKit shapes), wild.csv (3 cells outside [0, 1]), partial.csv (3 of the
    rig's 8 channels), and the in-range weights of wild.csv."""
    root = tmp_path_factory.mktemp("take_warnings")
    np.savez(
        root / "rig.npz",
        neutral=np.asarray(synthetic_rig.neutral),
        deltas=np.asarray(synthetic_rig.deltas),
        names=np.asarray(ARKIT),
        faces=np.asarray(synthetic_rig.faces),
        units=np.asarray("cm"),
    )
    rng = np.random.default_rng(5)
    weights = rng.uniform(0.0, 1.0, size=(16, 8)).astype(np.float32)
    wild = weights.copy()
    for (frame, channel), value in OUT_OF_RANGE.items():
        wild[frame, channel] = value
    write_livelink_csv(root / "wild.csv", capture_from_weights(wild, ARKIT, fps=30))
    partial = capture_from_weights(weights[:, [0, 3, 6]], [ARKIT[i] for i in (0, 3, 6)], fps=30)
    write_livelink_csv(root / "partial.csv", partial)
    return root, weights, wild


def _run(capsys, *argv):
    status = run_command([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.err


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("canrig: warning:")]


def _read(path, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        take = read_livelink_csv(path, **kwargs)
    return take, [str(w.message) for w in caught if issubclass(w.category, CanrigWarning)]


def _first_cell_line(path) -> int:
    """The file line (1-based) of the first row holding a value outside [0, 1]."""
    for number, line in enumerate(path.read_text().splitlines()[1:], start=2):
        if any(not 0.0 <= float(c) <= 1.0 for c in line.split(",")[2:]):
            return number
    raise AssertionError("no out-of-range cell")


def test_reader_clips_and_counts_out_of_range_cells(files):
    root, weights, wild = files
    take, messages = _read(root / "wild.csv", fps=30)
    [message] = [m for m in messages if "outside [0, 1]" in m]
    assert re.search(r"\b3 blendshape values outside \[0, 1\]", message)
    line = _first_cell_line(root / "wild.csv")
    assert line == 3 + 2  # frame 3 sits on line 5 (header on line 1)
    assert f"JawOpen = 7.5 on line {line}" in message and "clipped" in message
    assert take.weights.min() >= 0.0 and take.weights.max() <= 1.0
    column = {n: i for i, n in enumerate(take.names)}
    for (frame, channel), value in OUT_OF_RANGE.items():
        got = take.weights[frame, column[ARKIT[channel][0].upper() + ARKIT[channel][1:]]]
        assert got == np.clip(value, 0.0, 1.0)
    inside = np.ones(wild.shape, bool)
    for frame, channel in OUT_OF_RANGE:
        inside[frame, channel] = False
    np.testing.assert_array_equal(take.weights_for(ARKIT)[inside], wild[inside])


def test_reader_keeps_values_with_clip_false(files):
    root, _, wild = files
    take, messages = _read(root / "wild.csv", fps=30, clip=False)
    [message] = [m for m in messages if "outside [0, 1]" in m]
    assert "kept" in message and "clipped to" not in message
    np.testing.assert_array_equal(take.weights_for(ARKIT), wild)


def test_in_range_take_reads_without_a_range_warning(files, tmp_path):
    _, weights, _ = files
    write_livelink_csv(tmp_path / "ok.csv", capture_from_weights(weights, ARKIT, fps=30))
    _, messages = _read(tmp_path / "ok.csv", fps=30)
    assert not [m for m in messages if "outside" in m]


def test_weights_for_names_the_channels_a_take_lacks(files):
    root, weights, _ = files
    take, _ = _read(root / "partial.csv", fps=30)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = take.weights_for(ARKIT, missing="zero")
    [message] = [str(w.message) for w in caught if "no channel" in str(w.message)]
    absent = [ARKIT[i] for i in (1, 2, 4, 5, 7)]
    assert "5 of the rig's 8 shapes" in message and str(absent) in message
    np.testing.assert_array_equal(out[:, [1, 2, 4, 5, 7]], 0.0)
    np.testing.assert_allclose(out[:, [0, 3, 6]], weights[:, [0, 3, 6]], atol=1e-6)
    with pytest.raises(ValueError, match="no source channel"):
        take.weights_for(ARKIT, missing="raise")


def test_animate_warns_and_clips_unless_no_clip(files, capsys, tmp_path):
    root, _, wild = files
    rig = root / "rig.npz"
    for flag, expected in (("--clip", np.clip(wild, 0.0, 1.0)), ("--no-clip", wild)):
        out, meshes = tmp_path / f"anim{flag}.glb", tmp_path / f"meshes{flag}.npz"
        argv = ["animate", rig, root / "wild.csv", "-o", out, "--meshes", meshes, flag]
        status, err = _run(capsys, *argv)
        assert status == 0, err
        [line] = [w for w in _warnings(err) if "outside [0, 1]" in w]
        assert "3 blendshape values" in line and "JawOpen = 7.5" in line
        assert ("clipped" in line) == (flag == "--clip")
        with np.load(meshes) as z:
            np.testing.assert_allclose(z["weights"], expected, atol=1e-6)


def test_animate_names_the_missing_channels(files, capsys, tmp_path):
    root, _, _ = files
    argv = ["animate", root / "rig.npz", root / "partial.csv", "-o", tmp_path / "a.glb"]
    status, err = _run(capsys, *argv)
    assert status == 0, err
    [line] = [w for w in _warnings(err) if "no channel" in w]
    for name in ("eyeBlinkLeft", "eyeBlinkRight", "mouthSmileRight", "browInnerUp"):
        assert repr(name) in line
    assert "'jawOpen'" not in line  # the take has it
    argv[-1] = tmp_path / "b.glb"
    status, err = _run(capsys, *argv, "--missing", "raise")
    assert status == 2 and "no source channel" in err
    assert not (tmp_path / "b.glb").exists()


def test_retarget_warns_about_range_and_missing_channels(files, capsys, tmp_path):
    root, _, wild = files
    kept = [0, 3, 6]  # jawOpen (7.5 at frame 3), mouthSmileLeft, cheekPuff
    take = capture_from_weights(wild[:, kept], [ARKIT[i] for i in kept], fps=30)
    write_livelink_csv(tmp_path / "take.csv", take)
    common = ["retarget", tmp_path / "take.csv", "--from", root / "rig.npz", "--to-set", "arkit"]
    for flag in ("--clip", "--no-clip"):
        status, err = _run(capsys, *common, flag, "-o", tmp_path / f"out{flag}.csv")
        assert status == 0, err
        [line] = [w for w in _warnings(err) if "outside [0, 1]" in w]
        assert "1 blendshape values" in line and "JawOpen = 7.5" in line
        assert ("clipped" in line) == (flag == "--clip")
        [line] = [w for w in _warnings(err) if "no channel" in w]
        assert "'mouthFunnel'" in line and "'eyeBlinkLeft'" in line
        assert "'cheekPuff'" not in line and "'jawOpen'" not in line
    back, _ = _read(tmp_path / "out--clip.csv")
    solved = back.weights_for(["jawOpen", "cheekPuff"])
    assert abs(solved[3, 0] - 1.0) < 1e-2  # the 7.5 arrived clipped, and was solved as 1
    np.testing.assert_allclose(solved[:, 1], wild[:, 6], atol=1e-2)
