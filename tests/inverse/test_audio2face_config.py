"""``inverse.from_audio2face_config``: an Audio2Face-3D blendshape-solver JSON (the fields its
documentation lists for ``bs_skin_config.json``) read into ``Constrained``'s fields, on the
small synthetic rig named as ARKit/ICT controls."""

import json

import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.rig import BlendshapeRig

NAMES = (
    "jawLeft",
    "jawRight",
    "mouthLeft",
    "mouthRight",
    "eyeBlink_L",
    "eyeBlink_R",
    "browDownLeft",
    "browDownRight",
)


@pytest.fixture(scope="module")
def named(synthetic_rig):
    r = synthetic_rig
    return BlendshapeRig(r.neutral, r.deltas, r.correctives, NAMES, r.faces, units=r.units)


def _config(**changes):
    params = {
        "strengthL2regularization": 3.5,
        "strengthTemporalSmoothing": 5.0,
        "strengthL1regularization": 1.0,
        "strengthSymmetry": 100.0,
        "numPoses": 8,
        "bsSolveActivePoses": [1, 1, 1, 1, 1, 1, 1, 0],
        "bsSolveCancelPoses": [0, 0, 1, 1, -1, -1, -1, -1],
        "bsSolveSymmetryPoses": [-1, -1, -1, -1, 0, 0, 1, 1],
        "bsWeightMultipliers": [2.0, 1, 1, 1, 1, 1, 1.5, 1],
        "bsWeightOffsets": [0, 0, 0, 0, 0.2, 0, 0, 0],
        "templateBBSize": 20.0,
    }
    params.update(changes)
    return {"blendshape_params": {k: v for k, v in params.items() if v is not None}}


def _write(tmp_path, document, name="bs_skin_config.json"):
    path = tmp_path / name
    path.write_text(json.dumps(document))
    return path


def test_fields_map_onto_the_solver(tmp_path, named):
    path = _write(tmp_path, _config())
    method = inverse.from_audio2face_config(path, named)
    height = float(np.ptp(np.asarray(named.neutral)[:, 1]))
    scale = (height / 20.0) ** 2
    assert method.exclusive == ((0, 1), (2, 3))
    assert method.ties == ((4, 5), (6, 7))
    np.testing.assert_allclose(method.alpha, 1.0 * scale, rtol=1e-6)
    np.testing.assert_allclose(method.l2_weight, 3.5 * scale, rtol=1e-6)
    np.testing.assert_allclose(method.temporal_weight, 5.0 * scale, rtol=1e-6)
    np.testing.assert_allclose(method.tie_weight, 100.0 * scale, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(method.active), [1, 1, 1, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(np.asarray(method.multipliers), [2, 1, 1, 1, 1, 1, 1.5, 1])
    np.testing.assert_allclose(np.asarray(method.offsets), [0, 0, 0, 0, 0.2, 0, 0, 0], rtol=1e-7)
    # an explicit scale; the solve runs and honours the mask, offsets and cancel pairs
    method = inverse.from_audio2face_config(path, named, strength_scale=0.01)
    np.testing.assert_allclose(method.alpha, 0.01, rtol=1e-6)
    weights = np.asarray(inverse.solve(named, np.asarray(named.neutral), method).weights)
    assert weights[7] == 0.0 and weights[4] == pytest.approx(0.2)
    assert not (weights[0] > 0 and weights[1] > 0)


def test_poses_are_matched_by_name_and_unmapped_fields_are_named(tmp_path, named):
    # the configuration's poses in another order and in ARKit spelling, plus one pose the rig
    # lacks (inactive) and no entry for the rig's last shape
    poses = ["eyeBlinkRight", "eyeBlinkLeft", "jawLeft", "jawRight", "tongueOut", "mouthLeft"]
    document = _config(
        numPoses=6,
        bsSolveActivePoses=[1, 1, 1, 1, 0, 1],
        bsSolveCancelPoses=[-1, -1, 0, 0, -1, -1],
        bsSolveSymmetryPoses=[3, 3, -1, -1, -1, -1],
        bsWeightMultipliers=[1, 2, 1, 1, 1, 1],
        bsWeightOffsets=[0.0] * 6,
        tolerance=1e-10,
    )
    document["version"] = "2.3"
    path = _write(tmp_path, document)
    with pytest.warns(UserWarning) as caught:
        method = inverse.from_audio2face_config(path, named, pose_names=poses)
    messages = " ".join(str(w.message) for w in caught)
    assert "tolerance" in messages and "version" in messages  # unmapped fields, by name
    assert "mouthRight" in messages and "browDownLeft" in messages  # rig shapes not named
    assert method.exclusive == ((0, 1),) and method.ties == ((5, 4),)
    np.testing.assert_array_equal(np.asarray(method.active), [1, 1, 1, 0, 1, 1, 0, 0])
    np.testing.assert_array_equal(np.asarray(method.multipliers), [1, 1, 1, 1, 2, 1, 1, 1])


@pytest.mark.bad_input
def test_bad_configurations_are_named(tmp_path, named):
    def read(document, **kwargs):
        return inverse.from_audio2face_config(_write(tmp_path, document), named, **kwargs)

    with pytest.raises(ValueError, match="numPoses: the configuration is of another rig"):
        per_pose = ("bsSolveActivePoses", "bsWeightMultipliers", "bsWeightOffsets")
        pairs = {f: [-1] * 52 for f in ("bsSolveCancelPoses", "bsSolveSymmetryPoses")}
        read(_config(numPoses=52, **{f: [1] * 52 for f in per_pose}, **pairs))
    with pytest.raises(ValueError, match="bsWeightMultipliers: expected 8"):
        read(_config(bsWeightMultipliers=[1.0] * 7))
    with pytest.raises(ValueError, match="bsSolveCancelPoses: id 0 is shared by 3"):
        read(_config(bsSolveCancelPoses=[0, 0, 0, 1, 1, -1, -1, -1]))
    with pytest.raises(ValueError, match="strengthSymmetry"):
        read(_config(strengthSymmetry=-1.0))
    with pytest.raises(ValueError, match="missing fields \\['strengthL1regularization'\\]"):
        read(_config(strengthL1regularization=None))
    with pytest.raises(ValueError, match="pose_names: active poses the rig does not have"):
        poses = ["jawLeft", "jawRight", "mouthLeft", "mouthRight", "x", "y", "z", "w"]
        read(_config(), pose_names=poses)
    with pytest.raises(ValueError, match="path"):
        inverse.from_audio2face_config(tmp_path / "missing.json", named)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not JSON"):
        inverse.from_audio2face_config(tmp_path / "bad.json", named)
