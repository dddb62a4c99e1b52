"""Layering (section 5.2) and its handling of duplicated edit poses."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from canrig_jax.rig import evaluate, evaluate_batch
from canrig_jax.wpse import apply, apply_layered, fit_layered, fit_pose_space_edit
from canrig_jax.wpse._layers import assign_layers


def test_assign_layers_rule():
    poses = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.05], [0.0, 0.0], [1.0, 0.01]])
    assert assign_layers(poses, eta=0.1) == [0, 0, 1, 2, 1]
    assert assign_layers(poses, eta=0.0) == [0, 0, 0, 1, 0]
    with pytest.raises(ValueError, match="eta"):
        assign_layers(poses, eta=-1.0)


def test_distinct_edits_stay_in_one_layer(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    layered = fit_layered(tiny_rig, poses, edits, sigma=0.4, eta=0.01)
    single = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    assert layered.n_layers == 1
    w = np.full(tiny_rig.n_blendshapes, 0.4, np.float32)
    posed = evaluate(tiny_rig, w)
    np.testing.assert_allclose(apply_layered(layered, w, posed), apply(single, w, posed), atol=2e-5)


@pytest.mark.slow
def test_duplicated_pose_goes_to_a_new_layer_and_the_later_edit_wins(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    poses = np.concatenate([poses, poses[:1]])
    edits = np.concatenate([edits, -edits[:1]])  # re-sculpted differently at the same pose
    layered = fit_layered(tiny_rig, poses, edits, sigma=0.4, eta=0.05, layer_sigma=0.02)
    assert layered.n_layers == 2 and layered.assignment[-1] == 1
    posed = evaluate_batch(tiny_rig, poses)
    got = np.asarray(jax.vmap(apply_layered, (None, 0, 0))(layered, poses, posed) - posed)
    scale = np.abs(edits).max()
    np.testing.assert_allclose(got[-1], edits[-1], atol=1e-3 * scale)  # the new sculpt
    # the other edits are kept up to the new layer's reach at their poses
    np.testing.assert_allclose(got[1:-1], edits[1:-1], atol=0.05 * scale)


def test_layer_sigma_validation(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    poses = np.concatenate([poses, poses[:1], poses[:1]])
    edits = np.concatenate([edits, edits[:1], edits[:1]])
    with pytest.raises(ValueError, match="layer_sigma"):
        fit_layered(tiny_rig, poses, edits, sigma=0.4, eta=0.05, layer_sigma=[0.1])
    with pytest.raises(ValueError, match="sigma"):
        fit_layered(tiny_rig, poses, edits, sigma=0.4, eta=0.05, layer_sigma=-0.1)
