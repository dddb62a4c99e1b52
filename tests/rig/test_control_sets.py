"""Control sets of one mesh: names told apart by convention, a rig cut to a subset that gives
the full rig's meshes with the other shapes at 0."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import data_file
from canrig_jax.rig import (
    CONTROL_SETS,
    BlendshapeRig,
    control_set_of,
    evaluate_batch,
    load_fbx_rig,
    select_control_set,
)
from canrig_jax.rig._control_sets import select_blendshapes


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("AK_25_JawOpen", "arkit"),
        ("jawOpen", "arkit"),
        ("head:EyeBlinkLeft", "arkit"),
        ("AU_26_JawDrop", "facs"),
        ("AU_12_L_LipCornerPuller", "facs"),
        ("AU12", "facs"),
        ("SR_21_Jaw_Open", "sranipal"),
        ("blendShape1.SR_05_Eye_Left_Blink", "sranipal"),
        ("AA_VI_10_aa", "visemes"),
        ("HB_08_TongueOut", None),
        ("_Neutral", None),
        ("AUDIO", None),
    ],
)
def test_control_set_of_follows_the_naming_conventions(name, expected):
    assert control_set_of(name) == expected


def test_selected_shapes_give_the_full_rigs_meshes_with_the_others_at_zero(synthetic_rig):
    # keeps the pairs (0, 1) and (2, 3), the triplet and the quad; drops the pair (1, 4)
    names = ["shape3", "shape0", "shape1", "shape2"]
    sub = select_blendshapes(synthetic_rig, names)
    assert sub.names == tuple(names)
    assert [sub.n_correctives(order) for order in (2, 3, 4)] == [2, 1, 1]
    rng = np.random.default_rng(5)
    poses = rng.uniform(0.0, 1.0, size=(5, 4)).astype(np.float32)
    full = np.zeros((5, synthetic_rig.n_blendshapes), np.float32)
    full[:, synthetic_rig.index(names)] = poses
    np.testing.assert_allclose(
        evaluate_batch(sub, poses), evaluate_batch(synthetic_rig, full), atol=1e-5
    )
    assert sub.units == synthetic_rig.units and sub.faces is not None


def test_selection_errors_name_the_argument(synthetic_rig):
    with pytest.raises(ValueError, match=r"names: the rig has no blendshapes \['nope'\]"):
        select_blendshapes(synthetic_rig, ["shape0", "nope"])
    with pytest.raises(ValueError, match=r"names: repeated blendshape names \['shape1'\]"):
        select_blendshapes(synthetic_rig, ["shape1", "shape1"])
    with pytest.raises(ValueError, match="names: expected a sequence"):
        select_blendshapes(synthetic_rig, "shape0")
    with pytest.raises(ValueError, match="names: expected at least one"):
        select_blendshapes(synthetic_rig, [])
    with pytest.raises(ValueError, match=r"control_set: the rig has no 'facs' shape"):
        select_control_set(synthetic_rig, "facs")
    with pytest.raises(ValueError, match="control_set: expected one of"):
        select_control_set(synthetic_rig, "ARKit")


def test_rocketbox_holds_the_documented_control_sets(data_dir):
    # data README: 175 blend shapes: 15 visemes, FACS units, 42 SRanipal shapes, 52 ARKit ones
    rig = load_fbx_rig(data_file("rocketbox/Male_Adult_08_facial.fbx", data_dir), names="all")
    sets = {s: select_control_set(rig, s) for s in CONTROL_SETS}
    assert rig.n_blendshapes == 175
    assert sets["arkit"].n_blendshapes == 52 and sets["sranipal"].n_blendshapes == 42
    assert sets["visemes"].n_blendshapes == 15
    assert all(n.startswith("AU_") for n in sets["facs"].names)
    assert set(sets["arkit"].names) <= set(rig.names) and "jawOpen" in sets["arkit"].names
    # one mesh: every set keeps the file's neutral
    for subset in sets.values():
        np.testing.assert_array_equal(subset.neutral, rig.neutral)
    assert isinstance(sets["sranipal"], BlendshapeRig)
