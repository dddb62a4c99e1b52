"""``canrig invert --points FILE``: the inverse rig from a few points of the surface, on the
small synthetic rig with its 8 shapes named as ARKit controls (no data folder)."""

import json

import numpy as np
import pytest

from canrig_jax import run_command
from canrig_jax.data import read_livelink_csv
from canrig_jax.rig import evaluate_batch

ARKIT = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "mouthSmileRight",
         "browInnerUp", "cheekPuff", "mouthFunnel")  # fmt: skip


@pytest.fixture(scope="module")
def files(tmp_path_factory, synthetic_rig):
    """rig.npz (linear, ARKit names), points.json (60 barycentric points), points.npz
    (their positions over 6 frames) and the frames' weights."""
    root = tmp_path_factory.mktemp("invert_points")
    rig = synthetic_rig
    np.savez(
        root / "rig.npz",
        neutral=np.asarray(rig.neutral),
        deltas=np.asarray(rig.deltas),
        names=np.asarray(ARKIT),
        faces=np.asarray(rig.faces),
        units=np.asarray("cm"),
    )
    rng = np.random.default_rng(4)
    triangles = rng.choice(np.asarray(rig.faces).shape[0], 60, replace=False)
    barycentric = rng.dirichlet(np.ones(3), 60)
    (root / "points.json").write_text(
        json.dumps({"triangles": triangles.tolist(), "barycentric": barycentric.tolist()})
    )
    weights = rng.uniform(0, 1, (6, 8)).astype(np.float32)
    weights[weights < 0.3] = 0.0
    linear = type(rig)(rig.neutral, rig.deltas, (), ARKIT, rig.faces, units="cm")
    meshes = np.asarray(evaluate_batch(linear, weights))
    corners = np.asarray(rig.faces)[triangles]
    points = np.einsum("tnjd,nj->tnd", meshes[:, corners], barycentric).astype(np.float32)
    np.savez(root / "points.npz", meshes=points)
    return root, weights


def _run(capsys, *argv):
    status = run_command([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.mark.slow
def test_invert_from_points_recovers_the_weights(files, capsys):
    root, weights = files
    out = root / "take.csv"
    status, stdout, err = _run(
        capsys,
        *("invert", root / "rig.npz", root / "points.npz", "-o", out),
        *("--points", root / "points.json", "--alpha", "0", "--passes", "200", "--tol", "0"),
    )
    assert status == 0, err
    assert "60 points" in err and "6 frames x 60 points" in stdout
    take = read_livelink_csv(out)
    solved = take.weights_for(ARKIT, missing="zero")
    np.testing.assert_allclose(solved, weights, atol=5e-3)


@pytest.mark.bad_input
def test_bad_points_are_one_error_line(files, capsys, tmp_path):
    root, _ = files
    (tmp_path / "far.json").write_text(json.dumps({"vertices": [0, 10**6]}))
    (tmp_path / "none.json").write_text(json.dumps({"markers": [1, 2]}))
    for points, words in (
        (tmp_path / "far.json", "outside the rig's"),
        (tmp_path / "none.json", "expected 'vertices'"),
        (tmp_path / "missing.json", "missing.json"),
    ):
        status, _, err = _run(
            capsys,
            *("invert", root / "rig.npz", root / "points.npz", "-o", tmp_path / "t.csv"),
            *("--points", points),
        )
        assert status == 2 and "canrig: error:" in err and words in err, err
        assert "Traceback" not in err and not (tmp_path / "t.csv").exists()
    # points of another count than the positions
    (tmp_path / "ten.json").write_text(json.dumps({"vertices": list(range(10))}))
    status, _, err = _run(
        capsys,
        *("invert", root / "rig.npz", root / "points.npz", "-o", tmp_path / "t.csv"),
        *("--points", tmp_path / "ten.json"),
    )
    assert status == 2 and "MESHES" in err, err
