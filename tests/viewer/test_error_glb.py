"""``export_error_glb``: an experiment's error written as vertex colour, on real data.

The take: four Live Link frames on the linear ICT face rig; the error of each frame is how far
the linear rig is from the ict-quartic rig (its correctives' contribution, in mm), a real
per-vertex error with a clear worst vertex. The file is re-read with a parser of the GLB
layout written here (NumPy only), not the writer's code.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from canrig_jax._metrics import CM_TO_MM, per_vertex_distance
from canrig_jax.rig import evaluate_batch, find_gltf_validator, load_gltf_rig, validate_gltf
from canrig_jax.viewer import export_error_glb, inspect_glb, save_error_legend

ROOT = Path(__file__).resolve().parents[2]


def _color_0(path) -> np.ndarray:
    """(V, 3) COLOR_0 of the first primitive, read from the GLB chunks and accessor tables."""
    data = Path(path).read_bytes()
    json_length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20 : 20 + json_length])
    blob = data[20 + json_length + 8 :]
    attributes = document["meshes"][0]["primitives"][0]["attributes"]
    accessor = document["accessors"][attributes["COLOR_0"]]
    assert (accessor["type"], accessor["componentType"]) == ("VEC3", 5126)
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    return np.frombuffer(blob, "<f4", accessor["count"] * 3, start).reshape(-1, 3)


@pytest.fixture(scope="module")
def take(ict_face, ict_quartic, livelink_weights):
    frames = livelink_weights[[20, 60, 100, 140]]
    meshes = np.asarray(evaluate_batch(ict_face, frames))
    error = per_vertex_distance(meshes, np.asarray(evaluate_batch(ict_quartic, frames))) * CM_TO_MM
    return meshes, error


def test_colours_encode_the_error(ict_face, take, tmp_path):
    """Read back: redness never decreases with the mean error, the default scale saturates
    the worst 5 % (full red) and the calmest vertex is the palest; on a scale up to the
    largest error the one reddest vertex is the worst. Each key shows its frame."""
    meshes, error = take
    mean = error.mean(axis=0)
    assert mean.max() > 2 * np.percentile(mean, 95)  # a real, local error: a clear worst
    times = np.array([0.0, 0.5, 1.0, 1.5])
    glb = export_error_glb(
        tmp_path / "error.glb", meshes, ict_face.faces, error, times=times, neutral=ict_face.neutral
    )
    colors = _color_0(glb.path)
    assert colors.shape == (ict_face.n_vertices, 3)
    np.testing.assert_allclose(glb.vertex_error_mm, mean)
    assert glb.vmax_mm == pytest.approx(np.percentile(mean, 95))
    assert glb.worst_vertex == int(np.argmax(mean))
    assert glb.worst_frame == int(np.argmax(error[:, glb.worst_vertex]))
    redness = colors[:, 0] - colors[:, 1:].mean(axis=1)
    order = np.argsort(mean, kind="stable")
    assert np.all(np.diff(redness[order]) >= 0)
    np.testing.assert_allclose(redness[mean >= glb.vmax_mm], 1.0)
    assert np.all(redness[mean < glb.vmax_mm] < 1.0)
    fade = 1 - mean / glb.vmax_mm  # white at 0: the calmest vertex is the palest
    np.testing.assert_allclose(colors[np.argmin(mean)], [1, fade.max(), fade.max()], rtol=1e-6)

    full = export_error_glb(
        tmp_path / "full.glb", meshes, ict_face.faces, error, vmax_mm=float(mean.max())
    )
    full_redness = _color_0(full.path)[:, 0] - _color_0(full.path)[:, 1:].mean(axis=1)
    assert np.flatnonzero(full_redness == full_redness.max()).tolist() == [full.worst_vertex]
    assert full.worst_vertex == glb.worst_vertex
    assert np.all(np.diff(full_redness[order]) >= 0)

    summary = inspect_glb(glb.path)
    assert summary.has_colors and len(summary.morph_names) == 4
    baked = load_gltf_rig(glb.path)
    np.testing.assert_allclose(baked.neutral, ict_face.neutral)
    np.testing.assert_allclose(baked.neutral + baked.deltas, meshes, atol=1e-5)
    if find_gltf_validator() is not None:
        report = validate_gltf(glb.path)
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:10]
        assert report["info"]["animationCount"] == 1


def test_region_and_scale(ict_face, take, tmp_path):
    """The worst vertex is sought in ``region`` only; ``vmax_mm`` sets full red."""
    meshes, error = take
    mean = error.mean(axis=0)
    region = mean < np.percentile(mean, 50)  # the calmer half: the global worst is outside
    glb = export_error_glb(
        tmp_path / "r.glb", meshes, ict_face.faces, error, region=region, vmax_mm=0.1
    )
    assert region[glb.worst_vertex] and glb.worst_vertex != int(np.argmax(mean))
    assert mean[glb.worst_vertex] == mean[region].max()
    colors = _color_0(glb.path)
    np.testing.assert_allclose(colors[mean >= 0.1], [[1.0, 0.0, 0.0]] * int((mean >= 0.1).sum()))
    legend = save_error_legend(tmp_path / "legend.png", glb.vmax_mm)
    picture = np.asarray(Image.open(legend).convert("RGB"), float)
    row = picture[int(0.3 * picture.shape[0])]  # through the bar
    bar = np.flatnonzero(row.std(axis=1) > 0)  # coloured pixels (white to red)
    left, right = row[bar.min() + 3], row[bar.max() - 3]
    assert left.min() > 240 and right[0] > 240 and right[1:].max() < 40, (left, right)


@pytest.mark.bad_input
def test_bad_input_names_the_argument(ict_face, take, tmp_path):
    meshes, error = take
    faces = ict_face.faces
    for kwargs, name in (
        ({"error_mm": -error}, "error_mm"),
        ({"error_mm": error[:2]}, "error_mm"),
        ({"error_mm": error * np.nan}, "error_mm"),
        ({"meshes": meshes[0]}, "meshes"),
        ({"region": np.zeros(meshes.shape[1], bool)}, "region"),
        ({"neutral": meshes[0, :10]}, "neutral"),
        ({"vmax_mm": 0.0}, "vmax"),
        ({"error_mm": np.zeros_like(error)}, "vmax"),  # no error: nothing sets the scale
        ({"times": np.zeros(4)}, "times"),
    ):
        args = {"meshes": meshes, "error_mm": error} | kwargs
        with pytest.raises(ValueError, match=name):
            export_error_glb(
                tmp_path / "bad.glb", args.pop("meshes"), faces, args.pop("error_mm"), **args
            )
    assert not (tmp_path / "bad.glb").exists()


@pytest.mark.slow
def test_view_error_script_reproduces_the_standard_run(tmp_path):
    """``experiments/view_error.py wpse`` (about a minute): the take it recomputes has the
    standard run's error level, and its glb validates."""
    out = tmp_path / "wpse"
    subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "view_error.py"), "wpse", "--out", str(out)],
        check=True,
        cwd=ROOT,
    )
    results = json.loads((out / "error_glb.json").read_text())
    check = results["check"]
    assert check["wpse_mean_mm_these_frames"] < check["linear_mean_mm_these_frames"]
    standard = check["wpse_mean_mm_standard_run_all_held_out"]
    assert abs(check["wpse_mean_mm_these_frames"] - standard) < 0.25 * standard
    assert (out / "error_legend.png").exists()
    assert results["glb"]["frames"] == 30
    if find_gltf_validator() is not None:
        assert validate_gltf(out / "error.glb")["issues"]["numErrors"] == 0
