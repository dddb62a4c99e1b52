"""UsdSkel output: the rig's blend shapes and a take's weights, re-read and evaluated by
usd-core's own UsdSkel machinery (BlendShapeQuery), against the glTF rig (skipped without the
optional usd-core)."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax import run_command
from canrig_jax.data import capture_from_weights, write_livelink_csv
from canrig_jax.rig import BlendshapeRig, export_gltf, export_usd, load_gltf_rig, load_usd_rig

pxr = pytest.importorskip("pxr")
ARKIT = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "mouthSmileRight",
         "browInnerUp", "cheekPuff", "mouthFunnel")  # fmt: skip


@pytest.fixture(scope="module")
def linear_rig(synthetic_rig):
    """The synthetic rig's blendshapes under ARKit names (UsdSkel has no correctives)."""
    return BlendshapeRig(synthetic_rig.neutral, synthetic_rig.deltas, (), ARKIT,
                         synthetic_rig.faces)  # fmt: skip


def _usd_points(path, time):
    """The mesh at ``time`` as usd-core's UsdSkel deforms it (its animation's weights)."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(stage.GetPrimAtPath("/Rig")), Usd.PrimDefaultPredicate)
    mesh = stage.GetPrimAtPath("/Rig/Face")
    query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh))
    skeleton = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skeleton")))
    weights = skeleton.GetAnimQuery().ComputeBlendShapeWeights(time)
    mapper = cache.GetSkinningQuery(mesh).GetBlendShapeMapper()
    weights = mapper.Remap(weights) if mapper else weights
    sub, shapes, subshapes = query.ComputeSubShapeWeights(weights)
    points = Vt.Vec3fArray(UsdGeom.Mesh(mesh).GetPointsAttr().Get())
    assert query.ComputeDeformedPoints(
        sub, shapes, subshapes, query.ComputeBlendShapePointIndices(),
        query.ComputeSubShapePointOffsets(), points,
    )  # fmt: skip
    return np.asarray(points, np.float64)


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_usd_round_trip_evaluates_to_the_gltf_rig(linear_rig, tmp_path, suffix):
    rng = np.random.default_rng(4)
    weights = rng.uniform(0, 1, size=(5, len(ARKIT)))
    export_gltf(linear_rig, tmp_path / "rig.glb")
    gltf = load_gltf_rig(tmp_path / "rig.glb")
    path = export_usd(linear_rig, tmp_path / f"rig{suffix}", weights=weights, fps=30.0)
    back, animation = load_usd_rig(path)
    assert back.names == ARKIT and back.units == "cm"
    np.testing.assert_allclose(animation, weights, atol=1e-7)
    np.testing.assert_array_equal(back.faces, np.asarray(linear_rig.faces))
    for frame in (0, 2, 4):
        want = np.asarray(gltf.neutral, np.float64) + np.einsum(
            "k,kvi->vi", weights[frame], np.asarray(gltf.deltas, np.float64)
        )
        np.testing.assert_allclose(_usd_points(path, frame), want, atol=1e-5)  # cm


def test_bad_names_and_weights_are_refused(linear_rig, tmp_path):
    named = BlendshapeRig(linear_rig.neutral, linear_rig.deltas, (),
                          ("a+b", *ARKIT[1:]), linear_rig.faces)  # fmt: skip
    with pytest.raises(ValueError, match="USD identifiers"):
        export_usd(named, tmp_path / "x.usda")
    with pytest.raises(ValueError, match="weights: expected"):
        export_usd(linear_rig, tmp_path / "x.usda", weights=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="path: expected one of"):
        export_usd(linear_rig, tmp_path / "x.usdz")
    assert list(tmp_path.iterdir()) == []


def test_animate_writes_a_skel_animation_at_the_takes_times(linear_rig, tmp_path, capsys):
    rng = np.random.default_rng(5)
    weights = rng.uniform(0, 1, size=(12, len(ARKIT))).astype(np.float32)
    write_livelink_csv(tmp_path / "take.csv", capture_from_weights(weights, ARKIT, fps=30))
    np.savez(tmp_path / "rig.npz", neutral=np.asarray(linear_rig.neutral),
             deltas=np.asarray(linear_rig.deltas), names=np.asarray(ARKIT),
             faces=np.asarray(linear_rig.faces))  # fmt: skip
    out = tmp_path / "anim.usda"
    argv = ["animate", tmp_path / "rig.npz", tmp_path / "take.csv", "-o", out, "--fps", "30"]
    status = run_command([str(a) for a in argv])
    assert status == 0, capsys.readouterr().err
    _, animation = load_usd_rig(out)
    np.testing.assert_allclose(animation, weights, atol=1e-6)
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == 30 and stage.GetEndTimeCode() == 11
    want = np.asarray(linear_rig.neutral) + np.einsum("k,kvi->vi", weights[7],
                                                      np.asarray(linear_rig.deltas))  # fmt: skip
    np.testing.assert_allclose(_usd_points(out, 7), want, atol=1e-5)
