"""Bad inputs of the data loaders: folders, part names, damaged files (named in the error)."""

from __future__ import annotations

import shutil
import types
from pathlib import Path

import numpy as np
import pytest

from canrig_jax import CorruptFileError
from canrig_jax.data import (
    ict_identity,
    load_fbx,
    load_head,
    load_ict,
    load_ict_obj_folder,
    load_livelinkface,
    load_mediapipe_face,
    read_livelink_csv,
    retarget_weights,
)
from canrig_jax.data._ict import load_identity_modes

from .conftest import handled, raises, run_case

FILES = {
    "ict": "ict-facekit/expressions.npz",
    "identity": "ict-facekit/identity.npz",
    "livelink": "livelinkface/dao_livelinkface.npz",
    "mediapipe": "mediapipe/canonical_face.npz",
}


def _damaged_folder(root: Path, data_dir: Path, damage) -> Path:
    """A copy of the data folder (links) whose four .npz files are damaged by ``damage``."""
    folder = root / damage.__name__
    for relative in FILES.values():
        target = folder / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(damage((data_dir / relative).read_bytes(), relative))
    return folder


def truncated(data: bytes, relative: str) -> bytes:
    return data[: len(data) // 2]


def not_a_zip(data: bytes, relative: str) -> bytes:
    return b"this is not an npz file\n" * 10


def flipped(data: bytes, relative: str) -> bytes:
    """200 bytes flipped in the compressed members: the zip CRC check fails."""
    array = bytearray(data)
    for i in np.random.default_rng(0).choice(np.arange(200, len(array) - 200), 200, False):
        array[i] ^= 0xFF
    return bytes(array)


def missing_array(data: bytes, relative: str) -> bytes:
    """The same file without its largest array (the one every loader reads)."""
    import io

    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    del arrays[max(arrays, key=lambda k: arrays[k].nbytes)]
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def nan_positions(data: bytes, relative: str) -> bytes:
    import io

    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if "neutral" in arrays:
        arrays["neutral"] = arrays["neutral"].copy()
        arrays["neutral"][5] = np.nan
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


@pytest.fixture(scope="module")
def ctx(data_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("damaged")
    folders = {
        damage.__name__: _damaged_folder(root, data_dir, damage)
        for damage in (truncated, not_a_zip, flipped, missing_array, nan_positions)
    }
    empty = root / "empty"
    empty.mkdir()
    return types.SimpleNamespace(data_dir=data_dir, damaged=folders, empty=empty, root=root)


LOADERS = {
    "ict": lambda d: load_ict(d),
    "identity": lambda d: load_identity_modes(d),
    "livelink": lambda d: load_livelinkface(d),
    "mediapipe": lambda d: load_mediapipe_face(d),
}


def _damaged_cases():
    for damage in ("truncated", "not_a_zip", "flipped", "missing_array"):
        for name, load in LOADERS.items():
            yield raises(
                f"{name}-{damage}",
                lambda c, load=load, damage=damage: load(c.damaged[damage]),
                CorruptFileError,
                Path(FILES[name]).name,
            )
    yield raises(
        "ict-nan-positions",
        lambda c: load_ict(c.damaged["nan_positions"]),
        CorruptFileError,
        "expressions.npz",
    )
    for name, load in LOADERS.items():
        yield raises(
            f"{name}-file-missing",
            lambda c, load=load: load(c.empty),
            FileNotFoundError,
            Path(FILES[name]).name,
        )


@pytest.mark.parametrize("case", list(_damaged_cases()))
def test_damaged_data_files(case, ctx):
    run_case(case, ctx)


LOAD_ICT = [
    raises("folder-missing", lambda c: load_ict(c.root / "nowhere"), FileNotFoundError, "data_dir"),
    raises("folder-not-a-path", lambda c: load_ict(42), TypeError, "data_dir"),
    raises("unknown-part", lambda c: load_ict(c.data_dir, parts=["Nose"]), ValueError, "parts"),
    raises("part-not-a-name", lambda c: load_ict(c.data_dir, parts=7), TypeError, "parts"),
    raises("no-parts", lambda c: load_ict(c.data_dir, parts=[]), ValueError, "parts"),
    handled(
        "part-as-string",
        lambda c: load_ict(c.data_dir, parts="Face"),
        lambda model, c: np.testing.assert_array_equal(
            model.neutral, load_ict(c.data_dir).neutral[:9409]
        ),
    ),
]


@pytest.mark.parametrize("case", LOAD_ICT)
def test_load_ict(case, ctx):
    run_case(case, ctx)


ICT_IDENTITY = [
    raises("nan", lambda c: ict_identity([np.nan, 0.0], c.data_dir), ValueError, "coefficients"),
    raises("2-d", lambda c: ict_identity(np.zeros((2, 2)), c.data_dir), ValueError, "coefficients"),
    raises(
        "too-many", lambda c: ict_identity(np.zeros(101), c.data_dir), ValueError, "coefficients"
    ),
    raises("none", lambda c: ict_identity([], c.data_dir), ValueError, "coefficients"),
    handled(
        "zero-identity-is-the-neutral",
        lambda c: ict_identity(np.zeros(3), c.data_dir),
        lambda head, c: np.testing.assert_allclose(head, load_ict(c.data_dir).neutral),
    ),
]


@pytest.mark.parametrize("case", ICT_IDENTITY)
def test_ict_identity(case, ctx):
    run_case(case, ctx)


def _obj_copy(c, names=("jawOpen",)):
    folder = c.root / "obj"
    if not folder.exists():
        shutil.copytree(c.data_dir / "ict-facekit" / "raw", folder)
    return folder


def _cut_obj(c, fraction: float) -> Path:
    """A copy of the raw ICT folder whose jawOpen.obj keeps only its first ``fraction``."""
    folder = c.root / f"obj_cut_{fraction}"
    if not folder.exists():
        shutil.copytree(c.data_dir / "ict-facekit" / "raw", folder)
        obj = folder / "jawOpen.obj"
        obj.chmod(0o644)
        data = obj.read_bytes()
        obj.write_bytes(data[: int(len(data) * fraction)])
    return folder


LOAD_ICT_OBJ_FOLDER = [
    raises(
        "folder-missing", lambda c: load_ict_obj_folder(c.root / "no"), FileNotFoundError, "folder"
    ),
    raises("no-neutral", lambda c: load_ict_obj_folder(c.empty), FileNotFoundError, "folder"),
    raises(
        "unknown-expression",
        lambda c: load_ict_obj_folder(_obj_copy(c), names=["notAShape"]),
        FileNotFoundError,
        "names",
    ),
    *(
        raises(
            f"truncated-obj-{fraction}",
            lambda c, fraction=fraction: load_ict_obj_folder(_cut_obj(c, fraction)),
            CorruptFileError,
            "jawOpen.obj is truncated",
        )
        for fraction in (0.0, 0.5, 0.9)  # empty; no faces (trimesh: KeyError); faces cut
    ),
]


@pytest.mark.parametrize("case", LOAD_ICT_OBJ_FOLDER)
def test_load_ict_obj_folder(case, ctx):
    run_case(case, ctx)


NAMES = ("EyeBlinkLeft", "JawOpen")
RETARGET = [
    raises(
        "complex-weights",
        lambda c: retarget_weights(np.array([[1j, 0.0]]), NAMES, ["eyeBlink_L"]),
        TypeError,
        "weights",
    ),
    raises(
        "nan-weights",
        lambda c: retarget_weights(np.array([[np.nan, 0.0]]), NAMES, ["eyeBlink_L"]),
        ValueError,
        "weights",
    ),
    raises(
        "bad-missing-mode",
        lambda c: retarget_weights(np.zeros((1, 2)), NAMES, ["eyeBlink_L"], missing="drop"),
        ValueError,
        "missing",
    ),
    raises(
        "names-as-one-string",
        lambda c: retarget_weights(np.zeros((1, 2)), NAMES, "eyeBlink_L"),
        ValueError,
        "target",
    ),
    raises(
        "unknown-target-channel",
        lambda c: retarget_weights(np.zeros((1, 2)), NAMES, ["noSuchShape"]),
        ValueError,
        "noSuchShape",
    ),
    handled(
        "reordered-by-name",
        lambda c: retarget_weights(np.array([[0.25, 0.75]]), NAMES, ["jawOpen", "eyeBlink_L"])[0],
        lambda out, c: np.testing.assert_array_equal(out, [[0.75, 0.25]]),
    ),
]


@pytest.mark.parametrize("case", RETARGET)
def test_retarget_weights(case, ctx):
    run_case(case, ctx)


_TRIANGLE_25CM_IN_M = "v 0 0 0\nv 0.25 0 0\nv 0 0.25 0\nf 1 2 3\n"


def _rocketbox(c) -> bytes:
    """The bytes of a Rocketbox FBX file (skips without it)."""
    path = c.data_dir / "rocketbox" / "Male_Adult_08_facial.fbx"
    if not path.is_file():
        pytest.skip(f"the data folder has no {path.name}")
    return path.read_bytes()


def _file(c, name: str, text: str | bytes) -> Path:
    path = c.root / "issue20" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


_HEADER = "Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen\n"

READ_LIVELINK_CSV = [
    raises("missing", lambda c: read_livelink_csv(c.root / "no.csv"), FileNotFoundError, "no.csv"),
    raises("not-a-path", lambda c: read_livelink_csv(3), TypeError, "path"),
    raises(
        "empty", lambda c: read_livelink_csv(_file(c, "e.csv", "")), ValueError, "e.csv, line 1"
    ),
    raises(
        "no-rows", lambda c: read_livelink_csv(_file(c, "n.csv", _HEADER)), ValueError, "no rows"
    ),
    raises(
        "bad-timecode",
        lambda c: read_livelink_csv(_file(c, "t.csv", _HEADER + "1:2:3,2,0,0\n")),
        ValueError,
        "t.csv, line 2: malformed timecode",
    ),
    raises(
        "non-numeric",
        lambda c: read_livelink_csv(_file(c, "v.csv", _HEADER + "00:00:00:01.000,2,0,zero\n")),
        ValueError,
        "v.csv, line 2: JawOpen = 'zero'",
    ),
    raises(
        "duplicated",
        lambda c: read_livelink_csv(
            _file(c, "d.csv", "Timecode,JawOpen,jawOpen\n00:00:00:01.000,0,0\n")
        ),
        ValueError,
        "duplicated channel",
    ),
    raises(
        "frame-over-fps",
        lambda c: read_livelink_csv(_file(c, "f.csv", _HEADER + "00:00:00:40.000,2,0,0\n"), fps=30),
        ValueError,
        "f.csv, line 2",
    ),
]


@pytest.mark.parametrize("case", READ_LIVELINK_CSV)
def test_read_livelink_csv(case, ctx):
    run_case(case, ctx)


LOAD_HEAD = [
    raises("missing", lambda c: load_head(c.root / "no.obj"), FileNotFoundError, "no.obj"),
    raises("folder", lambda c: load_head(c.empty), ValueError, "is not a file"),
    raises("empty", lambda c: load_head(_file(c, "e.obj", "")), ValueError, "e.obj is empty"),
    raises(
        "not-a-mesh", lambda c: load_head(_file(c, "x.ply", b"\x00\x01junk")), ValueError, "x.ply"
    ),
    raises(
        "unit", lambda c: load_head(_file(c, "u.obj", "v 0 0 0\n"), units="ft"), ValueError, "units"
    ),
    raises("extension", lambda c: load_head(_file(c, "h.stl", "x")), ValueError, "h.stl"),
    raises("fbx-not-fbx", lambda c: load_head(_file(c, "h.fbx", "x")), ValueError, "h.fbx"),
    raises(
        "unit-makes-no-head",  # 25 cm written in metres, stated as mm: 0.025 cm tall
        lambda c: load_head(_file(c, "m.obj", _TRIANGLE_25CM_IN_M), units="mm"),
        ValueError,
        "m.obj is 0.025 cm tall (longest side) with units='mm'",
    ),
    raises(
        "unit-hint",
        lambda c: load_head(_file(c, "m.obj", _TRIANGLE_25CM_IN_M), units="cm"),
        ValueError,
        "looks like metres: pass units='m'",
    ),
]

LOAD_FBX = [
    raises("missing", lambda c: load_fbx(c.root / "no.fbx"), FileNotFoundError, "no.fbx"),
    raises("not-a-path", lambda c: load_fbx(3), TypeError, "path"),
    raises("folder", lambda c: load_fbx(c.empty), ValueError, "is not a file"),
    raises("empty", lambda c: load_fbx(_file(c, "e.fbx", b"")), ValueError, "e.fbx is empty"),
    raises("text", lambda c: load_fbx(_file(c, "t.fbx", "notes\n")), ValueError, "t.fbx"),
    raises(
        "truncated-header",
        lambda c: load_fbx(_file(c, "h.fbx", b"Kaydara FBX Binary  \x00\x1a")),
        CorruptFileError,
        "h.fbx",
    ),
    raises(
        "truncated",
        lambda c: load_fbx(_file(c, "cut.fbx", _rocketbox(c)[: len(_rocketbox(c)) // 2])),
        CorruptFileError,
        "cut.fbx",
    ),
    raises(
        "mesh-type",
        lambda c: load_fbx(_file(c, "m.fbx", b"x"), mesh=3),
        TypeError,
        "mesh",
    ),
]


@pytest.mark.parametrize("case", LOAD_FBX)
def test_load_fbx(case, ctx):
    run_case(case, ctx)


@pytest.mark.parametrize("case", LOAD_HEAD)
def test_load_head(case, ctx):
    run_case(case, ctx)
