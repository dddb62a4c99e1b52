"""Bad inputs of the rig layer: rig arrays, weights, batches, rig files and glTF files."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest

from canrig_jax import CorruptFileError
from canrig_jax.mesh import subdivide
from canrig_jax.rig import (
    BlendshapeRig,
    Corrective,
    deformation_transfer,
    evaluate,
    evaluate_batch,
    export_animated_gltf,
    export_gltf,
    load_fbx_rig,
    load_gltf_rig,
    load_rig,
    remesh_rig,
    save_rig,
)

from .conftest import handled, raises, run_case

NEUTRAL = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
DELTAS = np.zeros((2, 4, 3), np.float32)
DELTAS[0, 2, 2], DELTAS[1, 1, 1] = 0.5, -0.25
FACES = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
PAIR = Corrective(np.array([[0, 1]]), np.array([1, 2]), np.full((1, 2, 3), 0.125, np.float32))


UNMAKEABLE = Path("/proc/canrig-no-such-folder")
"""A folder that cannot be created, even by root (procfs)."""


def _round_trip(c, rig):
    export_gltf(rig, c.root / "round_trip.glb")
    return load_gltf_rig(c.root / "round_trip.glb")


def _rig(**kw):
    args = dict(neutral=NEUTRAL, deltas=DELTAS, correctives=(PAIR,), names=("a", "b"), faces=FACES)
    args.update(kw)
    return BlendshapeRig(**args)


def _reference(weights):
    """The rig's mesh at ``weights`` in float64 NumPy (eq. (5) by hand)."""
    w = np.asarray(weights, np.float64)
    mesh = NEUTRAL + np.tensordot(w, DELTAS, 1)
    mesh[[1, 2]] += w[0] * w[1] * 0.125
    return mesh


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    root = tmp_path_factory.mktemp("rig_files")
    rig = _rig()
    save_rig(root / "rig.npz", rig)
    export_gltf(rig, root / "rig.glb")
    good_npz, good_glb = (root / "rig.npz").read_bytes(), (root / "rig.glb").read_bytes()
    (root / "truncated.npz").write_bytes(good_npz[: len(good_npz) // 2])
    (root / "truncated.glb").write_bytes(good_glb[: len(good_glb) // 2])
    (root / "garbage.glb").write_bytes(b"\x00" * 64)
    flipped = bytearray(good_glb)
    flipped[30:40] = b"#" * 10  # inside the JSON chunk
    (root / "flipped.glb").write_bytes(bytes(flipped))
    (root / "a_file").write_text("not a folder")
    return types.SimpleNamespace(rig=rig, root=root)


def _close(expected):
    return lambda mesh, c: np.testing.assert_allclose(np.asarray(mesh), expected, atol=1e-6)


BLENDSHAPE_RIG = [
    raises("nan-neutral", lambda c: _rig(neutral=np.full((4, 3), np.nan)), ValueError, "neutral"),
    raises("neutral-2-d", lambda c: _rig(neutral=NEUTRAL[:, :2]), ValueError, "neutral"),
    raises("deltas-size", lambda c: _rig(deltas=DELTAS[:, :3]), ValueError, "deltas"),
    raises("complex-deltas", lambda c: _rig(deltas=DELTAS + 1j), TypeError, "deltas"),
    raises("string-neutral", lambda c: _rig(neutral=NEUTRAL.astype(str)), TypeError, "neutral"),
    raises("float-faces", lambda c: _rig(faces=FACES + 0.5), TypeError, "faces"),
    raises("face-out-of-range", lambda c: _rig(faces=FACES + 2), ValueError, "faces"),
    raises("names-count", lambda c: _rig(names=("a",)), ValueError, "names"),
    raises("repeated-names", lambda c: _rig(names=("a", "a")), ValueError, "names"),
    raises(
        "corrective-index-out-of-range",
        lambda c: _rig(correctives=(Corrective([[0, 2]], [1], np.zeros((1, 1, 3))),)),
        ValueError,
        "correctives",
    ),
    raises(
        "corrective-repeats-a-shape",
        lambda c: Corrective([[1, 1]], [1], np.zeros((1, 1, 3))),
        ValueError,
        "indices",
    ),
    raises(
        "corrective-float-indices",
        lambda c: Corrective([[0.0, 1.5]], [1], np.zeros((1, 1, 3))),
        TypeError,
        "indices",
    ),
    raises(
        "corrective-nan",
        lambda c: Corrective([[0, 1]], [1], np.full((1, 1, 3), np.nan)),
        ValueError,
        "deltas",
    ),
    handled(
        "int32-arrays-become-float",
        lambda c: evaluate(
            _rig(
                neutral=NEUTRAL.astype(np.int32),
                deltas=2 * np.ones((2, 4, 3), np.int32),
                correctives=(),
            ),
            np.array([0.5, 0.25]),
        ),
        _close(NEUTRAL.astype(np.int32) + 1.5),
    ),
    handled(
        "big-endian-arrays",
        lambda c: evaluate(
            _rig(neutral=NEUTRAL.astype(">f4"), deltas=DELTAS.astype(">f4")), np.array([0.5, 1.0])
        ),
        _close(_reference([0.5, 1.0])),
    ),
    handled(
        "int64-faces",
        lambda c: _rig(faces=FACES.astype(np.int64)).faces,
        lambda faces, c: np.testing.assert_array_equal(faces, FACES),
    ),
]


@pytest.mark.parametrize("case", BLENDSHAPE_RIG)
def test_blendshape_rig(case, ctx):
    run_case(case, ctx)


EVALUATE = [
    raises("weights-shape", lambda c: evaluate(c.rig, np.zeros(3)), ValueError, "weights"),
    raises("weights-batch", lambda c: evaluate(c.rig, np.zeros((2, 2))), ValueError, "weights"),
    raises(
        "nan-weights", lambda c: evaluate(c.rig, np.array([np.nan, 0.0])), ValueError, "weights"
    ),
    raises(
        "inf-weights", lambda c: evaluate(c.rig, np.array([np.inf, 0.0])), ValueError, "weights"
    ),
    raises(
        "complex-weights",
        lambda c: evaluate(c.rig, np.array([0.5 + 1j, 0.0])),
        TypeError,
        "weights",
    ),
    raises("string-weights", lambda c: evaluate(c.rig, np.array(["a", "b"])), TypeError, "weights"),
    handled(
        "int32-weights",
        lambda c: evaluate(c.rig, np.array([1, 1], np.int32)),
        _close(_reference([1, 1])),
    ),
    handled(
        "bool-weights",
        lambda c: evaluate(c.rig, np.array([True, False])),
        _close(_reference([1, 0])),
    ),
    handled(
        "big-endian-weights",
        lambda c: evaluate(c.rig, np.array([0.5, 0.5], ">f8")),
        _close(_reference([0.5, 0.5])),
    ),
    handled(
        "list-weights", lambda c: evaluate(c.rig, [0.25, 1.0]), _close(_reference([0.25, 1.0]))
    ),
]


@pytest.mark.parametrize("case", EVALUATE)
def test_evaluate(case, ctx):
    run_case(case, ctx)


EVALUATE_BATCH = [
    raises("one-pose", lambda c: evaluate_batch(c.rig, np.zeros(2)), ValueError, "poses"),
    raises("pose-width", lambda c: evaluate_batch(c.rig, np.zeros((3, 3))), ValueError, "poses"),
    raises(
        "nan-row",
        lambda c: evaluate_batch(c.rig, np.array([[0, 0], [np.nan, 0]])),
        ValueError,
        "poses",
    ),
    raises(
        "complex", lambda c: evaluate_batch(c.rig, np.zeros((2, 2), complex)), TypeError, "poses"
    ),
    raises(
        "zero-chunk",
        lambda c: evaluate_batch(c.rig, np.zeros((2, 2)), chunk=0),
        ValueError,
        "chunk",
    ),
    raises(
        "float-chunk",
        lambda c: evaluate_batch(c.rig, np.zeros((2, 2)), chunk=1.5),
        ValueError,
        "chunk",
    ),
    raises("not-a-rig", lambda c: evaluate_batch(NEUTRAL, np.zeros((2, 2))), TypeError, "rig"),
    handled(
        "no-poses",
        lambda c: evaluate_batch(c.rig, np.zeros((0, 2))),
        lambda out, c: out.shape == (0, 4, 3) or pytest.fail(str(out.shape)),
    ),
    handled(
        "ragged-last-chunk",
        lambda c: evaluate_batch(c.rig, np.array([[1, 0], [0, 1], [1, 1.0]]), chunk=2),
        lambda out, c: np.testing.assert_allclose(
            out, np.stack([_reference(w) for w in ([1, 0], [0, 1], [1, 1])]), atol=1e-6
        ),
    ),
]


@pytest.mark.parametrize("case", EVALUATE_BATCH)
def test_evaluate_batch(case, ctx):
    run_case(case, ctx)


RIG_FILES = [
    raises(
        "load-missing", lambda c: load_rig(c.root / "missing.npz"), FileNotFoundError, "missing.npz"
    ),
    raises(
        "load-truncated",
        lambda c: load_rig(c.root / "truncated.npz"),
        CorruptFileError,
        "truncated.npz",
    ),
    raises(
        "load-not-npz", lambda c: load_rig(c.root / "garbage.glb"), CorruptFileError, "garbage.glb"
    ),
    raises("load-not-a-path", lambda c: load_rig(3), TypeError, "path"),
    raises("save-to-folder", lambda c: save_rig(c.root, c.rig), IsADirectoryError, "path"),
    raises(
        "save-under-a-file",
        lambda c: save_rig(c.root / "a_file" / "r.npz", c.rig),
        NotADirectoryError,
        "path",
    ),
    raises("save-not-a-rig", lambda c: save_rig(c.root / "r.npz", NEUTRAL), TypeError, "rig"),
    handled(
        "round-trip",
        lambda c: evaluate(load_rig(c.root / "rig.npz"), np.array([0.5, 0.5])),
        _close(_reference([0.5, 0.5])),
    ),
]


@pytest.mark.parametrize("case", RIG_FILES)
def test_rig_files(case, ctx):
    run_case(case, ctx)


GLTF = [
    raises(
        "load-missing",
        lambda c: load_gltf_rig(c.root / "missing.glb"),
        FileNotFoundError,
        "missing.glb",
    ),
    raises(
        "load-truncated",
        lambda c: load_gltf_rig(c.root / "truncated.glb"),
        CorruptFileError,
        "truncated.glb",
    ),
    raises(
        "load-flipped-json",
        lambda c: load_gltf_rig(c.root / "flipped.glb"),
        CorruptFileError,
        "flipped.glb",
    ),
    raises(
        "load-not-gltf", lambda c: load_gltf_rig(c.root / "garbage.glb"), ValueError, "garbage.glb"
    ),
    raises("load-not-a-path", lambda c: load_gltf_rig(None), TypeError, "path"),
    raises("export-to-folder", lambda c: export_gltf(c.rig, c.root), IsADirectoryError, "path"),
    raises(
        "export-under-a-file",
        lambda c: export_gltf(c.rig, c.root / "a_file" / "x.glb"),
        NotADirectoryError,
        "path",
    ),
    raises(
        "export-without-faces",
        lambda c: export_gltf(_rig(faces=None), c.root / "x.glb"),
        ValueError,
        "rig",
    ),
    raises("export-not-a-rig", lambda c: export_gltf(NEUTRAL, c.root / "x.glb"), TypeError, "rig"),
    raises(  # a folder even root cannot make: the temporary file's error names the output
        "export-to-a-folder-that-cannot-be-made",
        lambda c: export_gltf(c.rig, UNMAKEABLE / "x.glb"),
        FileNotFoundError,
        f"path: cannot write {UNMAKEABLE / 'x.glb'}",
    ),
    handled(
        "no-blendshapes-round-trip",
        lambda c: _round_trip(
            c, _rig(deltas=np.zeros((0, 4, 3), np.float32), names=(), correctives=())
        ),
        lambda back, c: (
            np.testing.assert_array_equal(back.neutral, NEUTRAL),
            np.testing.assert_array_equal(back.faces, FACES),
            np.testing.assert_array_equal(back.deltas, np.zeros((0, 4, 3))),
            np.testing.assert_array_equal(evaluate(back, np.zeros(0)), NEUTRAL),
        ),
    ),
    handled(
        "round-trip",
        lambda c: evaluate(load_gltf_rig(c.root / "rig.glb"), np.array([0.5, 0.5])),
        _close(_reference([0.5, 0.5])),
    ),
]


@pytest.mark.parametrize("case", GLTF)
def test_gltf(case, ctx):
    run_case(case, ctx)


def _fine():
    return subdivide(NEUTRAL, FACES)


RIGS_ON_OTHER_MESHES = [
    raises(
        "remesh-not-a-rig",
        lambda c: remesh_rig(NEUTRAL, subdivide(NEUTRAL, FACES)),
        TypeError,
        "rig",
    ),
    raises("remesh-not-remeshed", lambda c: remesh_rig(c.rig, NEUTRAL), TypeError, "remeshed"),
    raises(
        "remesh-other-mesh",
        lambda c: remesh_rig(c.rig, subdivide(_fine().vertices, _fine().faces)),
        ValueError,
        "remeshed",
    ),
    raises(
        "transfer-no-faces",
        lambda c: deformation_transfer(_rig(faces=None), NEUTRAL, None),
        ValueError,
        "source_rig",
    ),
    raises(
        "transfer-not-a-rig",
        lambda c: deformation_transfer(NEUTRAL, NEUTRAL, None),
        TypeError,
        "source_rig",
    ),
]


@pytest.mark.parametrize("case", RIGS_ON_OTHER_MESHES)
def test_rigs_on_other_meshes(case, ctx):
    run_case(case, ctx)


def _animated(c, weights, **kw):
    return export_animated_gltf(c.rig, weights, c.root / "anim.glb", **kw)


def _keys_read_back(path, c):
    """The morph weights written: the rig's 2 weights and the corrective's product."""
    from canrig_jax.rig._gltf_animation import morph_target_weights

    np.testing.assert_allclose(
        morph_target_weights(c.rig, np.array([[1.0, 0.5], [0.0, 2.0]])),
        [[1.0, 0.5, 0.5], [0.0, 2.0, 0.0]],
    )
    assert path.stat().st_size > 0


ANIMATED_GLTF = [
    raises("weights-1d", lambda c: _animated(c, np.zeros(2)), ValueError, "weights"),
    raises("weights-no-frames", lambda c: _animated(c, np.zeros((0, 2))), ValueError, "weights"),
    raises("weights-wrong-k", lambda c: _animated(c, np.zeros((3, 5))), ValueError, "weights"),
    raises("weights-nan", lambda c: _animated(c, np.full((3, 2), np.nan)), ValueError, "weights"),
    raises(
        "weights-complex", lambda c: _animated(c, np.zeros((3, 2), complex)), TypeError, "weights"
    ),
    raises("fps-zero", lambda c: _animated(c, np.zeros((3, 2)), fps=0.0), ValueError, "fps"),
    raises(
        "times-repeat",
        lambda c: _animated(c, np.zeros((3, 2)), times=np.array([0.0, 0.1, 0.1])),
        ValueError,
        "times",
    ),
    raises(
        "times-shape",
        lambda c: _animated(c, np.zeros((3, 2)), times=np.zeros(2)),
        ValueError,
        "times",
    ),
    raises(
        "rotation-shape",
        lambda c: _animated(c, np.zeros((3, 2)), head_rotation=np.zeros((3, 2))),
        ValueError,
        "head_rotation",
    ),
    raises(
        "under-a-file",
        lambda c: export_animated_gltf(c.rig, np.zeros((3, 2)), c.root / "a_file" / "x.glb"),
        NotADirectoryError,
        "path",
    ),
    raises(
        "not-a-rig",
        lambda c: export_animated_gltf(NEUTRAL, np.zeros((3, 2)), c.root / "x.glb"),
        TypeError,
        "rig",
    ),
    raises(
        "no-blendshapes",
        lambda c: export_animated_gltf(
            _rig(deltas=np.zeros((0, 4, 3)), names=(), correctives=()),
            np.zeros((3, 0)),
            c.root / "x.glb",
        ),
        ValueError,
        "rig: has no blendshapes",
    ),
    handled("weights-over-one", lambda c: _animated(c, np.full((2, 2), 2.0)), _keys_read_back),
]


@pytest.mark.parametrize("case", ANIMATED_GLTF)
def test_export_animated_gltf(case, ctx):
    run_case(case, ctx)


FBX_RIG = [
    raises("missing", lambda c: load_fbx_rig(c.root / "no.fbx"), FileNotFoundError, "no.fbx"),
    raises("names", lambda c: load_fbx_rig(c.root / "no.fbx", names="arkit"), ValueError, "names"),
    raises("crop", lambda c: load_fbx_rig(c.root / "no.fbx", crop="face"), ValueError, "crop"),
    raises("crop-type", lambda c: load_fbx_rig(c.root / "no.fbx", crop=[1]), ValueError, "crop"),
    raises("not-fbx", lambda c: load_fbx_rig(c.root / "rig.npz"), ValueError, "rig.npz"),
]


@pytest.mark.parametrize("case", FBX_RIG)
def test_load_fbx_rig(case, ctx):
    run_case(case, ctx)
