"""Live Link Face CSV: the app's layout, round trips, frame rate, drops, bad input."""

from __future__ import annotations

import dataclasses
import os
import warnings

import numpy as np
import pytest

from canrig_jax.data import (
    ARKIT_NAMES,
    LIVELINK_CSV_CHANNELS,
    capture_from_weights,
    format_timecode,
    load_ict,
    load_livelinkface,
    read_livelink_csv,
    to_arkit,
    write_livelink_csv,
)
from canrig_jax.data._livelink_csv import LIVELINK_ROTATIONS, parse_timecode


@pytest.fixture(scope="module")
def capture(data_dir):
    return load_livelinkface(data_dir)


@pytest.fixture(scope="module")
def take_csv(capture, tmp_path_factory):
    path = tmp_path_factory.mktemp("llf") / "take.csv"
    write_livelink_csv(path, capture)
    return path


def _read(path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_livelink_csv(path, **kwargs)


def _by_arkit(names, weights):
    return {to_arkit(n): weights[:, i] for i, n in enumerate(names)}


def test_header_is_the_apps(take_csv):
    header = take_csv.read_text().splitlines()[0].split(",")
    assert header[:2] == ["Timecode", "BlendShapeCount"]
    assert tuple(header[2:54]) == LIVELINK_CSV_CHANNELS
    assert tuple(header[54:]) == LIVELINK_ROTATIONS
    # the app's order differs from Unreal's enum in two places, and is Pascal case
    assert LIVELINK_CSV_CHANNELS[15:17] == ("JawRight", "JawLeft")
    assert LIVELINK_CSV_CHANNELS[21:23] == ("MouthRight", "MouthLeft")
    assert sorted(to_arkit(n) for n in LIVELINK_CSV_CHANNELS) == sorted(ARKIT_NAMES)
    row = take_csv.read_text().splitlines()[1].split(",")
    assert row[1] == "61"
    assert parse_timecode(row[0])[:4] == (0, 53, 15, 35)  # frame 5375735 at 60 fps, mod 24 h
    assert len(row[0]) == len("00:53:15:35.122")


def test_capture_round_trip(capture, take_csv):
    """The real capture written and read back: every value identical (float32)."""
    with pytest.warns(UserWarning, match="7 frames dropped at 60 fps in 1 gaps"):
        back = read_livelink_csv(take_csv)
    assert back.fps == 60.0 and back.n_frames == capture.n_frames == 180
    assert back.blendshape_count == 61
    original = _by_arkit(capture.names, capture.weights)
    read = _by_arkit(back.names, back.weights)
    assert original.keys() == read.keys()
    for name in original:
        np.testing.assert_array_equal(read[name], original[name], err_msg=name)
    assert back.rotation_names == LIVELINK_ROTATIONS == capture.rotation_names
    np.testing.assert_array_equal(back.head_eye_rotations, capture.head_eye_rotations)
    np.testing.assert_array_equal(back.frame_number, capture.frame_number % (86400 * 60))
    np.testing.assert_allclose(back.sub_frame, capture.sub_frame, atol=5e-4)


def test_written_file_reads_back_identically(take_csv, tmp_path):
    first = _read(take_csv)
    write_livelink_csv(tmp_path / "again.csv", first)
    assert (tmp_path / "again.csv").read_text() == take_csv.read_text()
    second = _read(tmp_path / "again.csv")
    for field in dataclasses.fields(first):
        a, b = getattr(first, field.name), getattr(second, field.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype, field.name
            np.testing.assert_array_equal(a, b, err_msg=field.name)
        else:
            assert a == b, field.name


def test_columns_matched_by_name(take_csv, tmp_path):
    """Shuffled columns, camelCase names, no rotations, BlendShapeCount 51 without TongueOut."""
    lines = [line.split(",") for line in take_csv.read_text().splitlines()]
    rng = np.random.default_rng(0)
    keep = [i for i in range(2, 53 + 1) if lines[0][i] != "TongueOut"]  # 51 shapes
    order = [0, 1, *rng.permutation(keep)]
    rows = []
    for r, cells in enumerate(lines):
        out = [cells[i] for i in order]
        if r == 0:
            out = out[:2] + [c[0].lower() + c[1:] for c in out[2:]]
        else:
            out[1] = "51"
        rows.append(",".join(out))
    (tmp_path / "shuffled.csv").write_text("\n".join(rows) + "\n")
    shuffled = _read(tmp_path / "shuffled.csv")
    full = _read(take_csv)
    assert shuffled.blendshape_count == 51 and shuffled.rotation_names == ()
    assert shuffled.head_eye_rotations.shape == (180, 0)
    assert len(shuffled.names) == 51 and "tongueOut" not in shuffled.names
    a, b = _by_arkit(shuffled.names, shuffled.weights), _by_arkit(full.names, full.weights)
    for name, column in a.items():
        np.testing.assert_array_equal(column, b[name])


def test_map_to_a_rig_never_drops_silently(take_csv, data_dir):
    take = _read(take_csv)
    ict = load_ict(data_dir)
    with pytest.warns(UserWarning, match="TongueOut"):
        weights = take.weights_for(ict.names)
    by_name = _by_arkit(take.names, take.weights)
    assert weights.shape == (180, len(ict.names))
    for j, name in enumerate(ict.names):  # both ICT halves take the single ARKit channel
        np.testing.assert_array_equal(weights[:, j], by_name[to_arkit(name)])


def _synthetic(tmp_path, timecodes, name="t.csv", header=None, values=None):
    header = header or ["Timecode", "BlendShapeCount", "EyeBlinkLeft", "JawOpen"]
    rows = [",".join(header)]
    for i, code in enumerate(timecodes):
        rows.append(",".join([code, "2", *(values or [f"{0.1 * i:.1f}", "0.5"])]))
    path = tmp_path / name
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("fps", [24, 25, 30, 60])
def test_frame_rate_inferred(tmp_path, fps):
    codes = [format_timecode(100 * fps + i, 0.0, fps) for i in range(2 * fps)]
    take = read_livelink_csv(_synthetic(tmp_path, codes))
    assert take.fps == fps
    np.testing.assert_array_equal(np.diff(take.frame_number), 1)


def test_drops_repeats_and_midnight(tmp_path):
    codes = ["23:59:59:58.000", "23:59:59:59.000", "00:00:00:00.000", "00:00:00:00.000"]
    codes += ["00:00:00:05.500"]
    with pytest.warns(UserWarning) as record:
        take = read_livelink_csv(_synthetic(tmp_path, codes), fps=60)
    messages = " ".join(str(w.message) for w in record)
    assert "4 frames dropped" in messages and "before lines [6]" in messages
    assert "1 repeated timecodes (lines [5])" in messages
    assert take.frame_number[2] - take.frame_number[1] == 1  # across midnight
    assert take.sub_frame[-1] == 0.5


def test_timecode_format():
    assert format_timecode(0, 0.0, 60) == "00:00:00:00.000"
    assert format_timecode(((14 * 60 + 3) * 60 + 52) * 30 + 28, 0.207, 30) == "14:03:52:28.207"
    assert parse_timecode("14:03:52:28.207") == (14, 3, 52, 28, 0.207)


BAD = {
    "malformed timecode": (["00:00:01:02.000", "00:00:1:03.000"], None, None, "line 3.*timecode"),
    "non-numeric": (
        ["00:00:01:02.000", "00:00:01:03.000"],
        None,
        ["abc", "0.5"],
        "line 2.*EyeBlinkLeft = 'abc' is not a number",
    ),
    "duplicated channel": (
        ["00:00:01:02.000"],
        ["Timecode", "BlendShapeCount", "EyeBlinkLeft", "eyeBlinkLeft"],
        None,
        "line 1.*duplicated channel 'eyeBlinkLeft'",
    ),
    "no rows": ([], None, None, "no rows after the header"),
    "unknown column": (
        ["00:00:01:02.000"],
        ["Timecode", "BlendShapeCount", "EyeBlinkLeft", "Smile"],
        None,
        "line 1.*'Smile'",
    ),
    "short row": (["00:00:01:02.000"], None, ["0.1"], "line 2: 3 values, the header has 4"),
    "not finite": (["00:00:01:02.000"], None, ["nan", "0.1"], "line 2.*EyeBlinkLeft = 'nan'"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_names_file_and_line(tmp_path, case):
    codes, header, values, message = BAD[case]
    path = _synthetic(tmp_path, codes, header=header, values=values)
    with pytest.raises(ValueError, match=message) as info:
        read_livelink_csv(path)
    assert str(path) in str(info.value)


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.csv"):
        read_livelink_csv(tmp_path / "missing.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(ValueError, match="empty.csv, line 1: empty file"):
        read_livelink_csv(tmp_path / "empty.csv")
    (tmp_path / "binary.csv").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ValueError, match="binary.csv"):
        read_livelink_csv(tmp_path / "binary.csv")
    with pytest.raises(ValueError, match="fps"):
        read_livelink_csv(_synthetic(tmp_path, ["00:00:01:02.000"]), fps=0)


def test_write_is_atomic_and_checked(capture, tmp_path):
    target = tmp_path / "keep.csv"
    target.write_text("precious")
    broken = dataclasses.replace(capture, weights=np.full_like(capture.weights, np.nan))
    with pytest.raises(ValueError, match="non-finite"):
        write_livelink_csv(target, broken)
    assert target.read_text() == "precious"
    assert sorted(os.listdir(tmp_path)) == ["keep.csv"]  # no temporary left behind
    (tmp_path / "afile").write_text("x")
    with pytest.raises(NotADirectoryError, match="afile"):
        write_livelink_csv(tmp_path / "afile" / "take.csv", capture)


def test_solved_weights_to_csv(tmp_path, data_dir):
    """ICT-named weights (split halves averaged first) written in the app's layout."""
    weights = np.random.default_rng(1).uniform(0, 1, (5, 3)).astype(np.float32)
    take = capture_from_weights(weights, ["eyeBlink_L", "jawOpen", "browInnerUp"], fps=30)
    write_livelink_csv(tmp_path / "s.csv", take)
    back = _read(tmp_path / "s.csv", fps=30)
    assert back.names == ("EyeBlinkLeft", "JawOpen", "BrowInnerUp")
    np.testing.assert_array_equal(back.weights, weights)
    assert back.blendshape_count == 3 and back.fps == 30
    with pytest.raises(ValueError, match="share one ARKit name"):
        write_livelink_csv(
            tmp_path / "x.csv", capture_from_weights(weights[:, :2], ["cheekPuff_L", "cheekPuff_R"])
        )


def _timecodes(path):
    return [line.split(",", 1)[0] for line in path.read_text().splitlines()[1:]]


def test_timecodes_and_gaps_survive_every_csv_written_from_a_take(take_csv, tmp_path):
    """The real capture with 20 more rows dropped (a second gap, besides its own 7-frame
    one): read -> write -> read keeps every timecode, and solved weights given the take's
    timecodes (``capture_from_weights(..., timecodes=take)``) are written with them."""
    lines = take_csv.read_text().splitlines()
    (tmp_path / "gap.csv").write_text("\n".join(lines[:101] + lines[121:]) + "\n")
    with pytest.warns(UserWarning, match="27 frames dropped at 60 fps in 2 gaps"):
        take = read_livelink_csv(tmp_path / "gap.csv")
    assert take.n_frames == 160 and sorted(np.diff(take.frame_number))[-2:] == [8, 21]
    write_livelink_csv(tmp_path / "again.csv", take)
    assert _timecodes(tmp_path / "again.csv") == _timecodes(tmp_path / "gap.csv")
    np.testing.assert_array_equal(_read(tmp_path / "again.csv").frame_number, take.frame_number)

    solved = capture_from_weights(take.weights[:, :3], take.names[:3], timecodes=take)
    write_livelink_csv(tmp_path / "solved.csv", solved)
    assert _timecodes(tmp_path / "solved.csv") == _timecodes(tmp_path / "gap.csv")
    back = _read(tmp_path / "solved.csv")
    assert back.fps == 60.0
    np.testing.assert_array_equal(back.frame_number, take.frame_number)
    np.testing.assert_array_equal(back.sub_frame, take.sub_frame)
    # without timecodes: consecutive frames from 00:00:00:00
    plain = capture_from_weights(take.weights[:, :3], take.names[:3])
    write_livelink_csv(tmp_path / "plain.csv", plain)
    assert _timecodes(tmp_path / "plain.csv")[:2] == ["00:00:00:00.000", "00:00:00:01.000"]


@pytest.mark.bad_input
def test_timecodes_must_match_the_weights(take_csv):
    take = _read(take_csv)
    with pytest.raises(ValueError, match="timecodes: the take has 180 frames, the weights 179"):
        capture_from_weights(take.weights[1:], take.names, timecodes=take)
    with pytest.raises(ValueError, match="fps: 30 differs"):
        capture_from_weights(take.weights, take.names, fps=30, timecodes=take)
    with pytest.raises(TypeError, match="timecodes: expected a LiveLinkCapture"):
        capture_from_weights(take.weights, take.names, timecodes=take.frame_number)
