"""Animated glTF: Khronos validator, and the weights re-read by an independent parser."""

from __future__ import annotations

import json
import os
import struct
import warnings

import numpy as np
import pytest

from canrig_jax.data import load_livelinkface
from canrig_jax.rig import (
    BlendshapeRig,
    Corrective,
    evaluate_batch,
    export_animated_gltf,
    find_gltf_validator,
    load_gltf_rig,
    validate_gltf,
)
from canrig_jax.rig._gltf_animation import head_rotation_quaternions, morph_target_weights


def read_glb(path) -> tuple[dict, dict]:
    """An independent GLB reader (the spec's layout, NumPy only): the JSON document and every
    accessor as an array (sparse accessors and strides are not used by the writer; refused)."""
    data = open(path, "rb").read()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    chunks, offset = {}, 12
    while offset < len(data):
        size, kind = struct.unpack_from("<II", data, offset)
        chunks[kind] = data[offset + 8 : offset + 8 + size]
        offset += 8 + size
    document = json.loads(chunks[0x4E4F534A])
    blob = chunks[0x004E4942]
    dtypes = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "u1"}
    widths = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
    arrays = {}
    for i, accessor in enumerate(document["accessors"]):
        assert "sparse" not in accessor
        view = document["bufferViews"][accessor["bufferView"]]
        assert "byteStride" not in view
        width = widths[accessor["type"]]
        start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
        count = accessor["count"] * width
        values = np.frombuffer(blob, dtypes[accessor["componentType"]], count, start)
        arrays[i] = values.reshape(accessor["count"], width)
    return document, arrays


@pytest.fixture(scope="module")
def small_quartic(ict_quartic):
    """ict-quartic with its first 20 correctives of each order (a small real rig, all orders)."""
    tables = []
    for table in ict_quartic.correctives:
        dense = table.to_dense(ict_quartic.n_vertices)[:20]
        tables.append(Corrective.from_dense(np.asarray(table.indices)[:20], dense))
    return BlendshapeRig(
        ict_quartic.neutral, ict_quartic.deltas, tables, ict_quartic.names, ict_quartic.faces
    )


@pytest.fixture(scope="module")
def take(small_quartic, data_dir):
    capture = load_livelinkface(data_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TongueOut: ICT has none (warned by weights_for)
        weights = capture.weights_for(small_quartic.names)
    return capture, weights


@pytest.fixture(scope="module")
def animated(small_quartic, take, tmp_path_factory):
    capture, weights = take
    path = tmp_path_factory.mktemp("gltf") / "anim.glb"
    times = (capture.frame_number - capture.frame_number[0]) / capture.fps  # gaps kept
    export_animated_gltf(
        small_quartic, weights, path, times=times, head_rotation=capture.head_eye_rotations[:, :3]
    )
    return path, times


def test_khronos_validator_zero_errors(animated):
    if find_gltf_validator() is None:
        pytest.skip(
            "Node.js or the npm package gltf-validator is missing: npm install gltf-validator"
        )
    report = validate_gltf(animated[0])
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:10]
    assert report["info"]["animationCount"] == 1
    assert report["info"]["totalVertexCount"] == 9409


def test_weights_frame_by_frame(small_quartic, take, animated):
    """Re-read independently: key times, morph weights (correctives = products of their
    drivers), named targets, and the mesh at each key equals evaluate(rig, w)."""
    capture, weights = take
    path, times = animated
    document, arrays = read_glb(path)
    animation = document["animations"][0]
    by_path = {
        c["target"]["path"]: animation["samplers"][c["sampler"]] for c in animation["channels"]
    }
    mesh = document["meshes"][0]
    names = mesh["extras"]["targetNames"]
    n_targets = len(mesh["primitives"][0]["targets"])
    assert names[:53] == list(small_quartic.names) and n_targets == 53 + 60
    keys = arrays[by_path["weights"]["input"]][:, 0]
    np.testing.assert_allclose(keys, times, atol=1e-6)
    assert keys[6] - keys[5] == pytest.approx(8 / 60, abs=1e-6)  # the capture's 8-frame gap
    morph = arrays[by_path["weights"]["output"]].reshape(len(keys), n_targets)
    np.testing.assert_array_equal(morph[:, :53], weights)
    for corrective in mesh["extras"]["correctives"]:
        drivers = [names.index(d) for d in corrective["drivers"]]
        expected = np.prod(weights[:, drivers].astype(np.float64), axis=1)
        np.testing.assert_allclose(morph[:, corrective["target"]], expected, rtol=1e-6, atol=1e-9)
    # the glTF mesh at each key, blended with the spec's linear formula, is the rig's
    primitive = mesh["primitives"][0]
    base = arrays[primitive["attributes"]["POSITION"]].astype(np.float64)
    targets = np.stack([arrays[t["POSITION"]] for t in primitive["targets"]]).astype(np.float64)
    frames = [0, 60, 179]
    glb_meshes = base + np.einsum("tn,nvc->tvc", morph[frames].astype(np.float64), targets)
    rig_meshes = np.asarray(evaluate_batch(small_quartic, weights[frames]))
    assert np.abs(glb_meshes - rig_meshes).max() < 1e-4  # cm: float32 sums
    rotation = arrays[by_path["rotation"]["output"]]
    np.testing.assert_allclose(
        rotation, head_rotation_quaternions(capture.head_eye_rotations[:, :3]), atol=1e-7
    )
    np.testing.assert_allclose(np.linalg.norm(rotation, axis=1), 1, atol=1e-6)
    # our own loader still reads the rig (units recorded)
    back = load_gltf_rig(path)
    assert back.units == "cm" and back.n_blendshapes == 53


def test_quaternion_closed_form():
    q = head_rotation_quaternions(np.array([[np.pi / 2, 0, 0], [0, np.pi / 2, 0], [0, 0, 0]]))
    s = np.sqrt(0.5)
    np.testing.assert_allclose(q, [[0, s, 0, s], [s, 0, 0, s], [0, 0, 0, 1]], atol=1e-7)


def test_morph_weights_closed_form(small_quartic):
    w = np.random.default_rng(0).uniform(0, 1, (4, 53))
    morph = morph_target_weights(small_quartic, w)
    i, j = np.asarray(small_quartic.correctives[0].indices)[3]
    np.testing.assert_allclose(morph[:, 53 + 3], w[:, i] * w[:, j], rtol=1e-6)


@pytest.mark.bad_input
def test_bad_input(small_quartic, take, tmp_path):
    _, weights = take
    with pytest.raises(ValueError, match="weights: expected shape"):
        export_animated_gltf(small_quartic, weights[:, :10], tmp_path / "a.glb")
    bad = weights.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="weights: contains non-finite"):
        export_animated_gltf(small_quartic, bad, tmp_path / "a.glb")
    with pytest.raises(ValueError, match="times: key times must increase"):
        export_animated_gltf(small_quartic, weights, tmp_path / "a.glb", times=np.zeros(180))
    with pytest.raises(ValueError, match="head_rotation"):
        export_animated_gltf(small_quartic, weights, tmp_path / "a.glb", head_rotation=np.zeros(3))
    (tmp_path / "afile").write_text("x")
    with pytest.raises(NotADirectoryError, match="afile"):
        export_animated_gltf(small_quartic, weights, tmp_path / "afile" / "a.glb")
    assert sorted(os.listdir(tmp_path)) == ["afile"]  # nothing partial left
