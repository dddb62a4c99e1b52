"""``canrig retarget``: a Live Link Face take carried onto another control set of one mesh.

A small rig (the synthetic sheet, no data folder) holds 8 ARKit shapes and 8 "SRanipal" shapes
that are the ARKit ones permuted and scaled, so the retargeted curves have a closed form. The
ARKit -> ARKit round trip must give the take back, in a CSV the project's Live Link reader
parses; the real Rocketbox head is ``-m slow``.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from canrig_jax import run_command
from canrig_jax.data import (
    capture_from_weights,
    data_file,
    load_livelinkface,
    read_livelink_csv,
    write_livelink_csv,
)
from canrig_jax.rig import load_gltf_rig

ARKIT = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "mouthSmileRight",
         "browInnerUp", "cheekPuff", "mouthFunnel")  # fmt: skip
ORDER = np.array([3, 0, 7, 5, 1, 6, 2, 4])
SCALE = np.linspace(1.0, 2.0, 8).astype(np.float32)
SRANIPAL = tuple(f"SR_{i + 1:02d}_Shape{i}" for i in range(8))


@pytest.fixture(scope="module")
def files(tmp_path_factory, synthetic_rig):
    """rig.npz (ARKit and SRanipal shapes on one mesh), take.csv (20 frames, head rotations),
    and the take's weights."""
    root = tmp_path_factory.mktemp("retarget")
    arkit = np.asarray(synthetic_rig.deltas)
    sranipal = arkit[ORDER] * SCALE[:, None, None]
    np.savez(
        root / "rig.npz",
        neutral=np.asarray(synthetic_rig.neutral),
        deltas=np.concatenate([arkit, sranipal]),
        names=np.asarray(ARKIT + SRANIPAL),
        faces=np.asarray(synthetic_rig.faces),
        units=np.asarray("cm"),
    )
    rng = np.random.default_rng(2)
    weights = rng.uniform(0.0, 1.0, size=(20, 8)).astype(np.float32)
    weights[rng.uniform(size=weights.shape) < 0.3] = 0.0
    rotations = rng.uniform(-0.3, 0.3, size=(20, 3)).astype(np.float32)
    take = capture_from_weights(
        weights,
        ARKIT,
        fps=30,
        head_eye_rotations=rotations,
        rotation_names=("HeadYaw", "HeadPitch", "HeadRoll"),
        start_frame=1250,  # crosses a second: the rate reads from the timecodes
    )
    write_livelink_csv(root / "take.csv", take)
    return root, weights, rotations


def _run(capsys, *argv):
    status = run_command([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _timecodes(path):
    return [line.split(",", 1)[0] for line in path.read_text().splitlines()[1:]]


@pytest.mark.slow
def test_arkit_to_arkit_gives_the_take_back_as_a_live_link_csv(files, capsys):
    root, weights, rotations = files
    out = root / "back.csv"
    argv = ("retarget", root / "take.csv", "--from", root / "rig.npz", "--to-set", "arkit")
    status, stdout, err = _run(capsys, *argv, "-o", out)
    assert status == 0, err
    back = read_livelink_csv(out)  # the project's reader parses what the command wrote
    np.testing.assert_allclose(back.weights_for(ARKIT), weights, atol=1e-3)
    np.testing.assert_array_equal(back.head_eye_rotations, rotations)
    assert _timecodes(out) == _timecodes(root / "take.csv") and back.fps == 30
    assert "per-frame RMSE mean" in stdout and "[" in err  # progress on stderr


def test_another_control_set_gets_the_closed_form_curves(files, capsys):
    root, weights, rotations = files
    out = root / "sranipal.csv"
    argv = ("retarget", root / "take.csv", "--from", root / "rig.npz", "--to-set", "sranipal")
    status, _, err = _run(capsys, *argv, "-o", out, "--quiet")
    assert status == 0 and err == "", err
    lines = out.read_text().splitlines()
    header = lines[0].split(",")
    assert header == ["Timecode", "BlendShapeCount", *SRANIPAL, "HeadYaw", "HeadPitch", "HeadRoll"]
    values = np.array([line.split(",")[1:] for line in lines[1:]], np.float64)
    assert np.all(values[:, 0] == 11)  # 8 controls and 3 rotations, as the app counts
    # the SRanipal shape j is the ARKit shape ORDER[j] scaled by SCALE[j]
    np.testing.assert_allclose(values[:, 1:9], weights[:, ORDER] / SCALE, atol=1e-3)
    np.testing.assert_array_equal(values[:, 9:].astype(np.float32), rotations)
    assert _timecodes(out) == _timecodes(root / "take.csv")


def test_a_glb_holds_the_target_controls(files, capsys):
    root, _, _ = files
    out = root / "sranipal.glb"
    argv = ("retarget", root / "take.csv", "--from", root / "rig.npz", "--to-set", "sranipal")
    status, _, err = _run(capsys, *argv, "-o", out, "--quiet")
    assert status == 0, err
    rig = load_gltf_rig(out)
    assert rig.names == SRANIPAL and rig.n_vertices == 400


def test_bad_input_is_one_error_line_and_nothing_written(files, capsys, tmp_path):
    root, _, _ = files
    out = tmp_path / "out.csv"
    base = ("retarget", root / "take.csv", "--from", root / "rig.npz", "-o", out)
    status, _, err = _run(capsys, *base, "--to-set", "facs")
    assert status == 2 and "canrig: error: --to-set facs: " in err and "no 'facs' shape" in err
    status, _, err = _run(capsys, *base, "--from-set", "sranipal", "--to-set", "arkit")
    assert status == 2 and "--from-set sranipal: the take drives ARKit controls" in err
    with np.load(root / "rig.npz") as z:
        np.savez(tmp_path / "small.npz", **{k: z[k] for k in ("names", "units")},
                 neutral=z["neutral"][:-1], deltas=z["deltas"][:, :-1])  # fmt: skip
    status, _, err = _run(capsys, *base, "--to", tmp_path / "small.npz", "--to-set", "arkit")
    assert status == 2 and f"--to {tmp_path / 'small.npz'}: target_rig: has 399" in err
    status, _, err = _run(capsys, *base[:-2], "-o", tmp_path / "out.obj", "--to-set", "arkit")
    assert status == 2 and "expected a .csv or .glb" in err
    assert not out.exists() and "Traceback" not in err


@pytest.mark.slow  # ~15 s: the real Rocketbox head and the 180-frame capture
def test_rocketbox_capture_round_trips_through_the_command(data_dir, tmp_path, capsys):
    take = tmp_path / "take.csv"
    write_livelink_csv(take, load_livelinkface(data_dir))
    fbx = data_file("rocketbox/Female_Adult_01_facial.fbx", data_dir)
    out = tmp_path / "back.csv"
    status, stdout, err = _run(
        capsys, "retarget", take, "--from", fbx, "--to-set", "arkit", "-o", out
    )
    assert status == 0, err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the take's dropped frames
        source, back = read_livelink_csv(take), read_livelink_csv(out)
    assert _timecodes(out) == _timecodes(take)
    names = [n for n in source.names]
    error = np.abs(back.weights_for(names) - source.weights)
    # the mesh is matched to float32 precision; nearly parallel shapes trade a little weight
    assert np.median(error) < 1e-3 and error.max() < 0.25
    rmse = float(stdout.split("per-frame RMSE mean ")[1].split(" mm")[0])
    assert rmse < 0.01
