"""Live Link Face CSV takes: read and write the layout Epic's iOS app exports.

The app writes one header line and one row per captured frame::

    Timecode,BlendShapeCount,EyeBlinkLeft,EyeLookDownLeft,...,TongueOut,HeadYaw,HeadPitch,
    HeadRoll,LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll
    14:03:52:28.207,61,0.0123,0.0,...

- ``Timecode`` is ``HH:MM:SS:FF.mmm``: hours, minutes, seconds, the frame ``FF`` within the
  second at the take's frame rate, and the sub-frame (a fraction of a frame) with 3 decimals.
- ``BlendShapeCount`` is 61 in the app's takes (52 ARKit shapes + 9 head and eye rotations);
  other tools write 51 or 52. It is kept, not trusted: the columns are matched by name.
- 52 ARKit channels in Pascal case, in the app's order (``LIVELINK_CSV_CHANNELS``; note
  ``JawRight`` before ``JawLeft`` and ``MouthRight`` before ``MouthLeft``, unlike Unreal's
  ``EARFaceBlendShape``), then the 9 rotations (``LIVELINK_ROTATIONS``).

``read_livelink_csv`` accepts the columns in any order (matched by name in any of the ARKit,
Unreal or ICT spellings), a subset of the channels, and missing rotation columns; it infers
the frame rate from the timecodes and warns about dropped and repeated frames.
``write_livelink_csv`` writes the app's layout; its output reads back identically, timecodes
included: a take read from a CSV keeps every timecode (and every dropped-frame gap) through
any CSV written from it, and ``capture_from_weights(..., timecodes=take)`` gives solved
weights the timecodes of the take they came from.
"""

import math
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float

from .._io import check_output_path, save_text
from .._warnings import warn
from ._livelinkface import LiveLinkCapture
from ._names import ARKIT_NAMES, to_arkit

LIVELINK_CSV_CHANNELS: tuple[str, ...] = tuple(
    n[0].upper() + n[1:]
    for n in (
        *ARKIT_NAMES[:14],
        "jawForward", "jawRight", "jawLeft", "jawOpen",
        "mouthClose", "mouthFunnel", "mouthPucker", "mouthRight", "mouthLeft",
        *ARKIT_NAMES[23:],
    )
)  # fmt: skip
"""The 52 blendshape columns in the order the Live Link Face app writes them."""

LIVELINK_ROTATIONS: tuple[str, ...] = (
    "HeadYaw", "HeadPitch", "HeadRoll",
    "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
    "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)  # fmt: skip
"""The head and eye rotation columns the app writes after the blendshapes."""

FRAME_RATES: tuple[int, ...] = (24, 25, 30, 48, 50, 60, 120)
"""Frame rates a timecode's frame field is checked against (the app records 30 or 60)."""

SECONDS_PER_DAY = 86400
_TIMECODE = re.compile(r"^(\d{2}):(\d{2}):(\d{2}):(\d{2,3})(?:\.(\d{1,6}))?$")


def parse_timecode(text: str) -> tuple[int, int, int, int, float]:
    """``(hours, minutes, seconds, frame, sub_frame)`` of ``HH:MM:SS:FF[.mmm]``; ValueError
    (naming the text) when it is not a timecode."""
    match = _TIMECODE.match(text.strip())
    if match is None:
        raise ValueError(f"malformed timecode {text!r}, expected HH:MM:SS:FF.mmm")
    h, m, s, f = (int(g) for g in match.groups()[:4])
    if h > 23 or m > 59 or s > 59:
        raise ValueError(f"malformed timecode {text!r}: hours < 24, minutes and seconds < 60")
    sub = float("0." + match.group(5)) if match.group(5) else 0.0
    return h, m, s, f, sub


def format_timecode(frame_number: int, sub_frame: float, fps: int) -> str:
    """``HH:MM:SS:FF.mmm`` of a frame count since midnight at ``fps`` (wraps at 24 h)."""
    frame_number = int(frame_number) % (SECONDS_PER_DAY * fps)
    seconds, frame = divmod(frame_number, fps)
    minutes, s = divmod(seconds, 60)
    h, m = divmod(minutes, 60)
    milli = min(int(round(float(sub_frame) * 1000)), 999)
    return f"{h:02d}:{m:02d}:{s:02d}:{frame:02d}.{milli:03d}"


def _format_value(x: np.float32) -> str:
    """Shortest decimal that reads back as the same float32."""
    return np.format_float_positional(np.float32(x), unique=True, trim="0")


def _where(path, line: int) -> str:
    return f"{path}, line {line}"


def _infer_fps(stamps: np.ndarray, path) -> int:
    """The smallest standard rate above every frame field seen; a take that never crosses a
    second cannot show its rate: the app's default, 60, is assumed (with a warning)."""
    top = int(stamps[:, 3].max()) + 1
    seconds = (stamps[:, 0] * 60 + stamps[:, 1]) * 60 + stamps[:, 2]
    if np.all(seconds == seconds[0]) and top <= 60:
        warn(
            f"{path}: the take never crosses a second, so its frame rate cannot be read from "
            "the timecodes; assuming the app's default 60 fps (pass fps= to choose)",
        )
        return 60
    for rate in FRAME_RATES:
        if rate >= top:
            return rate
    raise ValueError(f"{path}: a timecode frame field of {top - 1} exceeds every known rate")


def _check_sequence(frame_number: np.ndarray, fps: int, path) -> None:
    """Warn about dropped (a step over one frame), repeated and backward timecodes."""
    step = np.diff(frame_number)
    line = lambda i: int(i) + 3  # row i + 1 of the data sits on line i + 3 (header is line 1)
    dropped = np.flatnonzero(step > 1)
    repeated = np.flatnonzero(step == 0)
    backward = np.flatnonzero(step < 0)
    if dropped.size:
        lost = int((step[dropped] - 1).sum())
        warn(
            f"{path}: {lost} frames dropped at {fps} fps in {dropped.size} gaps (before lines "
            f"{[line(i) for i in dropped[:10]]}); rows are kept as found, not resampled",
        )
    if repeated.size:
        warn(
            f"{path}: {repeated.size} repeated timecodes (lines "
            f"{[line(i) for i in repeated[:10]]}); rows are kept as found",
        )
    if backward.size:
        warn(
            f"{path}: the timecode goes backwards at lines {[line(i) for i in backward[:10]]}",
        )


def read_livelink_csv(
    path: str | os.PathLike, fps: int | None = None, *, clip: bool = True
) -> LiveLinkCapture:
    """Read a Live Link Face CSV take.

    Args:
        path: the ``.csv`` file.
        fps: the take's frame rate; ``None`` infers it from the timecodes (the smallest of
            ``FRAME_RATES`` above every frame field; a take that never crosses a second is
            ambiguous: 60, the app's default, with a warning).
        clip: blendshape weights are 0..1; a cell outside that range is warned about (how
            many cells, and the first one's line and channel) and clipped to [0, 1], or, with
            ``clip=False``, warned about and kept. Rotation columns are never clipped.

    Returns:
        A ``LiveLinkCapture``: ``weights`` (T, K) float32 and ``names`` the K blendshape
        columns as spelled in the file, in file order; ``head_eye_rotations`` (T, R) and
        ``rotation_names`` the rotation columns found (R = 0 when the file has none);
        ``frame_number`` frames since midnight, ``sub_frame``, ``fps`` and
        ``blendshape_count`` as written. Map the channels onto a rig with
        ``capture.weights_for(rig.names)`` (warns about channels the rig does not read).

    Raises:
        FileNotFoundError naming ``path``; ValueError naming the file and line for an empty
        file, a header without ``Timecode`` or with an unknown or duplicated channel, a
        malformed timecode, a non-numeric or non-finite value, a row of the wrong length,
        and a file with no rows.
    """
    path, lines = _read_lines(path, fps)
    header, shapes, rotations, count_column = _parse_header(lines[0], path)
    rows = [(i + 1, line) for i, line in enumerate(lines) if i > 0 and line.strip()]
    if not rows:
        raise ValueError(f"{path}: no rows after the header (an empty take)")
    values, stamps, sub_frame, counts = _parse_rows(rows, header, count_column, path)
    blendshape_count = _blendshape_count(counts, rows, count_column, shapes, rotations, path)
    fps, frame_number = _frame_numbers(stamps, fps, rows, path)
    _check_sequence(frame_number, fps, path)
    weights = _check_range(values[:, shapes], [header[c] for c in shapes], rows, clip, path)
    return LiveLinkCapture(
        weights=np.ascontiguousarray(weights),
        names=tuple(header[c] for c in shapes),
        head_eye_rotations=np.ascontiguousarray(values[:, rotations]),
        rotation_names=tuple(header[c] for c in rotations),
        frame_number=frame_number,
        fps=float(fps),
        sub_frame=np.round(sub_frame, 3),
        blendshape_count=blendshape_count,
    )


def _check_range(weights, names, rows, clip: bool, path) -> np.ndarray:
    """``weights`` clipped to [0, 1] (``clip``) or kept, with a warning naming how many cells
    lie outside and the first of them (in file order)."""
    outside = (weights < 0) | (weights > 1)
    if not outside.any():
        return weights
    r, c = (int(i[0]) for i in np.nonzero(outside))
    what = "clipped to [0, 1]" if clip else "kept as they are (clip=False)"
    warn(
        f"{path}: {int(outside.sum())} blendshape values outside [0, 1] (the first: "
        f"{names[c]} = {weights[r, c]:g} on line {rows[r][0]}); {what}",
    )
    return np.clip(weights, 0.0, 1.0) if clip else weights


def _read_lines(path, fps) -> tuple[Path, list[str]]:
    """(the checked ``path``, its lines; the first one not blank)."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: Live Link Face CSV {path} not found")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, int) or fps < 1):
        raise ValueError(f"fps: expected a positive integer frame rate, got {fps!r}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not a text CSV file ({error})") from error
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise ValueError(f"{_where(path, 1)}: empty file, expected a Live Link Face header")
    return path, lines


def _parse_header(first_line: str, path):
    """(header cells, blendshape columns, rotation columns, BlendShapeCount column or None)."""
    header = [c.strip() for c in first_line.split(",")]
    if header[:1] != ["Timecode"]:
        raise ValueError(
            f"{_where(path, 1)}: the first column must be 'Timecode', got {header[0]!r}"
        )
    seen: dict[str, str] = {}
    shapes, rotations, count_column = [], [], None
    for col, name in enumerate(header[1:], start=1):
        if name == "BlendShapeCount":
            key = name
        elif name in LIVELINK_ROTATIONS:
            key = name
        else:
            try:
                key = to_arkit(name)
            except ValueError:
                raise ValueError(
                    f"{_where(path, 1)}: column {col + 1} {name!r} is neither an ARKit "
                    f"blendshape nor one of {LIVELINK_ROTATIONS}"
                ) from None
        if key in seen:
            raise ValueError(
                f"{_where(path, 1)}: duplicated channel {name!r} (column {col + 1}; "
                f"{seen[key]!r} came first)"
            )
        seen[key] = name
        if name == "BlendShapeCount":
            count_column = col
        elif name in LIVELINK_ROTATIONS:
            rotations.append(col)
        else:
            shapes.append(col)
    if not shapes:
        raise ValueError(f"{_where(path, 1)}: no blendshape columns in the header")
    return header, shapes, rotations, count_column


def _parse_rows(rows, header, count_column, path):
    """Per row: (values (T, columns) float32, timecodes (T, 4) h m s f, sub-frames (T,),
    BlendShapeCount (T,), 0 without the column)."""
    n_frames = len(rows)
    values = np.zeros((n_frames, len(header)), np.float32)
    stamps = np.zeros((n_frames, 4), np.int64)
    sub_frame = np.zeros(n_frames, np.float64)
    counts = np.zeros(n_frames, np.int64)
    for r, (number, line) in enumerate(rows):
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != len(header):
            raise ValueError(
                f"{_where(path, number)}: {len(cells)} values, the header has {len(header)}"
            )
        try:
            h, m, s, f, sub_frame[r] = parse_timecode(cells[0])
        except ValueError as error:
            raise ValueError(f"{_where(path, number)}: {error}") from None
        stamps[r] = (h, m, s, f)
        for col in range(1, len(header)):
            try:
                value = float(cells[col])
            except ValueError:
                raise ValueError(
                    f"{_where(path, number)}: {header[col]} = {cells[col]!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise ValueError(f"{_where(path, number)}: {header[col]} = {cells[col]!r}")
            values[r, col] = value
        if count_column is not None:
            count = values[r, count_column]
            if count != int(count) or count < 0:
                raise ValueError(
                    f"{_where(path, number)}: BlendShapeCount = {cells[count_column]!r} is not "
                    "a count"
                )
            counts[r] = int(count)
    return values, stamps, sub_frame, counts


def _blendshape_count(counts, rows, count_column, shapes, rotations, path) -> int | None:
    """The take's BlendShapeCount (None without the column): one value, warned about when it
    matches no known layout."""
    if count_column is not None and np.any(counts != counts[0]):
        bad = rows[int(np.flatnonzero(counts != counts[0])[0])][0]
        raise ValueError(f"{_where(path, bad)}: BlendShapeCount changes within the take")
    blendshape_count = int(counts[0]) if count_column is not None else None
    if blendshape_count is not None and blendshape_count not in (
        51,
        52,
        61,
        len(shapes),
        len(shapes) + len(rotations),
    ):
        warn(
            f"{path}: BlendShapeCount {blendshape_count} matches neither the app's 61 nor the "
            f"{len(shapes)} blendshape columns found; the columns are read by name",
        )
    return blendshape_count


def _frame_numbers(stamps, fps, rows, path):
    """(fps, (T,) frames since midnight), a take that crosses midnight counted on."""
    if fps is None:
        fps = _infer_fps(stamps, path)
    elif stamps[:, 3].max() >= fps:
        bad = rows[int(np.argmax(stamps[:, 3]))][0]
        raise ValueError(f"{_where(path, bad)}: frame field {stamps[:, 3].max()} >= fps={fps}")
    h, m, s, f = stamps.T
    frame_number = ((h * 60 + m) * 60 + s) * fps + f
    day = SECONDS_PER_DAY * fps
    wrapped = np.flatnonzero(np.diff(frame_number) < -day // 2)  # the take crosses midnight
    for i in wrapped:
        frame_number[i + 1 :] += day
    return fps, frame_number


def write_livelink_csv(
    path: str | os.PathLike,
    capture: LiveLinkCapture,
    *,
    blendshape_count: int | None = None,
) -> Path:
    """Write ``capture`` as a Live Link Face CSV in the app's layout, atomically.

    Columns: ``Timecode``, ``BlendShapeCount``, the capture's blendshapes in the app's order
    (``LIVELINK_CSV_CHANNELS``, Pascal case; a capture in another spelling is renamed by ARKit
    name, ICT's split halves are refused: retarget them first), then its rotation columns in
    the app's order. Timecodes come from ``frame_number`` (frames since midnight, wrapped
    at 24 h) and ``sub_frame`` (3 decimals) at ``capture.fps``; values are written as the
    shortest decimals that read back as the same float32.

    Args:
        path: the ``.csv`` to write (its folder is created; nothing partial is left on error).
        capture: a ``LiveLinkCapture`` (``load_livelinkface()``, ``read_livelink_csv``, or
            one built from a rig's weights).
        blendshape_count: the ``BlendShapeCount`` column (default: the capture's own, else
            61 as the app writes when all 52 shapes and 9 rotations are present, else the
            number of blendshape and rotation columns written).
    """
    check_output_path(path)
    if not isinstance(capture, LiveLinkCapture):
        raise TypeError(f"capture: expected a LiveLinkCapture, got {type(capture).__name__}")
    fps = capture.fps
    if not float(fps).is_integer() or fps < 1:
        raise ValueError(f"capture: fps must be a positive whole frame rate, got {fps}")
    fps = int(fps)
    weights = np.asarray(capture.weights, np.float32)
    rotations = np.asarray(capture.head_eye_rotations, np.float32)
    t = capture.n_frames
    if t == 0:
        raise ValueError("capture: no frames to write")
    if weights.shape != (t, len(capture.names)):
        raise ValueError(
            f"capture: weights {weights.shape} do not match {len(capture.names)} names"
        )
    if rotations.shape != (t, len(capture.rotation_names)):
        raise ValueError(
            f"capture: head_eye_rotations {rotations.shape} do not match "
            f"{len(capture.rotation_names)} rotation names"
        )
    for name, array in (("weights", weights), ("head_eye_rotations", rotations)):
        if not np.all(np.isfinite(array)):
            raise ValueError(f"capture: {name} contains non-finite values")
    canonical = [to_arkit(n) for n in capture.names]
    if len(set(canonical)) != len(canonical):
        raise ValueError(
            f"capture: several channels share one ARKit name ({capture.names}); ICT's split "
            "halves must be retarget to one ARKit channel first (retarget_weights)"
        )
    unknown_rotations = [n for n in capture.rotation_names if n not in LIVELINK_ROTATIONS]
    if unknown_rotations:
        raise ValueError(f"capture: unknown rotation channels {unknown_rotations}")
    column = {c: i for i, c in enumerate(canonical)}
    shape_order = [
        (name, column[to_arkit(name)]) for name in LIVELINK_CSV_CHANNELS if to_arkit(name) in column
    ]
    rotation_column = {n: i for i, n in enumerate(capture.rotation_names)}
    rotation_order = [(n, rotation_column[n]) for n in LIVELINK_ROTATIONS if n in rotation_column]
    if blendshape_count is None:
        blendshape_count = capture.blendshape_count
    if blendshape_count is None:
        full = len(shape_order) == 52 and len(rotation_order) == 9
        blendshape_count = 61 if full else len(shape_order) + len(rotation_order)
    frame_number = np.asarray(capture.frame_number, np.int64)
    sub_frame = (
        np.zeros(t) if capture.sub_frame is None else np.asarray(capture.sub_frame, np.float64)
    )
    if frame_number.shape != (t,) or sub_frame.shape != (t,):
        raise ValueError(f"capture: frame_number and sub_frame must have shape ({t},)")

    header = ["Timecode", "BlendShapeCount"]
    header += [name for name, _ in shape_order] + [name for name, _ in rotation_order]
    out = [",".join(header)]
    shape_idx = [i for _, i in shape_order]
    rot_idx = [i for _, i in rotation_order]
    for r in range(t):
        cells = [
            format_timecode(int(frame_number[r]), float(sub_frame[r]), fps),
            str(int(blendshape_count)),
        ]
        cells += [_format_value(x) for x in weights[r, shape_idx]]
        cells += [_format_value(x) for x in rotations[r, rot_idx]]
        out.append(",".join(cells))
    return save_text(path, "\n".join(out) + "\n")


def capture_from_weights(
    weights: Float[ArrayLike, "T K"],
    names: Sequence[str],
    fps: float | None = None,
    *,
    head_eye_rotations: Float[ArrayLike, "T R"] | None = None,
    rotation_names: Sequence[str] = (),
    start_frame: int = 0,
    timecodes: LiveLinkCapture | None = None,
) -> LiveLinkCapture:
    """A ``LiveLinkCapture`` from (T, K) weights over ``names`` (any ARKit spelling), e.g.
    solved rig weights to be written with ``write_livelink_csv``.

    Args:
        weights: (T, K) weights, unitless.
        names: the K channel names.
        fps: the frame rate (default: the ``timecodes`` take's, else 60).
        head_eye_rotations: (T, R) rotations over ``rotation_names`` (default: none).
        start_frame: with no ``timecodes``, the frames are consecutive from this frame number
            (frames since midnight; 0 writes ``00:00:00:00``).
        timecodes: a take (e.g. ``read_livelink_csv`` of the capture the weights were solved
            from) whose ``frame_number``, ``sub_frame`` and ``fps`` are copied, gaps
            included; it must have T frames.
    """
    weights = np.asarray(weights, np.float32)
    if weights.ndim != 2 or weights.shape[1] != len(names):
        raise ValueError(f"weights: expected shape (T, {len(names)}), got {weights.shape}")
    t = weights.shape[0]
    if timecodes is not None:
        if not isinstance(timecodes, LiveLinkCapture):
            raise TypeError(
                f"timecodes: expected a LiveLinkCapture, got {type(timecodes).__name__}"
            )
        if timecodes.n_frames != t:
            raise ValueError(
                f"timecodes: the take has {timecodes.n_frames} frames, the weights {t}; "
                "timecodes are copied frame by frame"
            )
        if fps is not None and float(fps) != float(timecodes.fps):
            raise ValueError(
                f"fps: {fps} differs from the timecodes take's {timecodes.fps:g} fps; "
                "leave fps out to use the take's"
            )
        fps = timecodes.fps
        frame_number = np.asarray(timecodes.frame_number, np.int64).copy()
        sub_frame = (
            np.zeros(t)
            if timecodes.sub_frame is None
            else np.asarray(timecodes.sub_frame, np.float64).copy()
        )
    else:
        frame_number = start_frame + np.arange(t, dtype=np.int64)
        sub_frame = np.zeros(t)
    if head_eye_rotations is None:
        head_eye_rotations = np.zeros((t, len(rotation_names)), np.float32)
    return LiveLinkCapture(
        weights=weights,
        names=tuple(str(n) for n in names),
        head_eye_rotations=np.asarray(head_eye_rotations, np.float32),
        rotation_names=tuple(rotation_names),
        frame_number=frame_number,
        fps=60.0 if fps is None else float(fps),
        sub_frame=sub_frame,
    )
