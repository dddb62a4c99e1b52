"""Exclusion pairs matched by ARKit name in any spelling, and synthesis thresholds in the rig's
unit, on the real ICT and MakeHuman channel lists."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import data_file, to_arkit
from canrig_jax.rig import (
    MUTUALLY_EXCLUSIVE,
    BlendshapeRig,
    SynthesisOptions,
    exclusive_pairs,
    ict_linear_rig,
    random_sparse_poses,
    synthesize_correctives,
)


@pytest.fixture(scope="module")
def makehuman_names(data_dir):
    with np.load(data_file("makehuman/hm08_face.npz", data_dir), allow_pickle=False) as z:
        return [str(n) for n in z["names"]]


def test_every_exclusion_applies_in_ict_and_arkit_spelling(ict_face, makehuman_names):
    expected = {frozenset(map(to_arkit, pair)) for pair in MUTUALLY_EXCLUSIVE}
    for names in (list(ict_face.names), makehuman_names):
        pairs = exclusive_pairs(names)
        found = {frozenset((to_arkit(names[i]), to_arkit(names[j]))) for i, j in pairs}
        assert found == expected, names[:5]


def test_random_poses_never_hold_both_shapes_of_a_pair(makehuman_names):
    poses = random_sparse_poses(np.random.default_rng(0), 400, makehuman_names, (8, 20))
    for i, j in exclusive_pairs(makehuman_names):
        assert not np.any((poses[:, i] > 0) & (poses[:, j] > 0)), (i, j)


def test_synthesis_thresholds_follow_the_rig_unit(data_dir):
    """The same head in cm and in dm gets the same correctives (scaled by 1/10)."""
    linear = ict_linear_rig(data_dir)
    keep = np.asarray(linear.index(["jawOpen", "mouthSmile_L", "mouthFunnel", "mouthPucker"]))
    cm = BlendshapeRig(linear.neutral, linear.deltas[keep], (), [linear.names[i] for i in keep],
                       linear.faces)  # fmt: skip
    dm = BlendshapeRig(cm.neutral / 10, cm.deltas / 10, (), cm.names, cm.faces, units="dm")
    options = SynthesisOptions(max_order=2)
    rig_cm, report_cm = synthesize_correctives(cm, options, progress=False)
    rig_dm, report_dm = synthesize_correctives(dm, options, progress=False)
    assert report_cm.kept == report_dm.kept and report_cm.kept[2] > 0
    assert rig_dm.units == "dm"
    pairs_cm, pairs_dm = rig_cm.corrective(2), rig_dm.corrective(2)
    np.testing.assert_array_equal(np.asarray(pairs_cm.indices), np.asarray(pairs_dm.indices))
    dense_cm = pairs_cm.to_dense(cm.n_vertices)
    np.testing.assert_allclose(pairs_dm.to_dense(cm.n_vertices) * 10, dense_cm, atol=2e-4)


def test_save_load_keeps_the_rig_unit(data_dir, tmp_path):
    from canrig_jax.rig import evaluate, load_rig, save_rig

    linear = ict_linear_rig(data_dir)
    dm = BlendshapeRig(linear.neutral / 10, linear.deltas / 10, (), linear.names, linear.faces,
                       units="dm")  # fmt: skip
    loaded = load_rig(save_rig(tmp_path / "dm.npz", dm))
    assert loaded.units == "dm"
    weights = np.zeros(dm.n_blendshapes, np.float32)
    weights[list(dm.index(["jawOpen", "mouthSmile_L"]))] = (0.7, 0.4)
    np.testing.assert_array_equal(evaluate(loaded, weights), evaluate(dm, weights))
    # a file written before rigs had units holds ICT's centimetres
    with np.load(tmp_path / "dm.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "units"}
    np.savez(tmp_path / "old.npz", **arrays)
    assert load_rig(tmp_path / "old.npz").units == "cm"


def test_exclusive_pairs_is_exported_from_rig():
    import canrig_jax.rig as rig_package

    assert "exclusive_pairs" in rig_package.__all__
    assert rig_package.exclusive_pairs is exclusive_pairs
