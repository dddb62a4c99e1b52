"""2D supervision of RigAnyFace (issue 25) on a real ICT head: the 2D loss, the withheld 3D
rigs, bad input."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.autorig import RigAnyFaceTrainOptions, training_set
from canrig_jax.autorig._data import head_rig, make_head, pose_displacements, quartic_pose_set
from canrig_jax.autorig._supervision_2d import Supervision2DOptions, loss_2d, padded_faces, train_2d
from canrig_jax.data import load_ict


@pytest.fixture(scope="module")
def setup(data_dir, ict_quartic):
    head = load_ict(data_dir, parts=None)
    poses = quartic_pose_set(ict_quartic, {2: 2, 3: 0, 4: 0})
    displacements = pose_displacements(head_rig(ict_quartic, head), poses)
    rng = np.random.default_rng(5)
    heads = [
        make_head(head, displacements, rng.standard_normal(100), "decimate_400", name=f"h{i}")
        for i in range(2)
    ]
    return heads, poses


OPTS = Supervision2DOptions(image_size=16, yaw_degrees=(0.0,), poses_2d=2, faces_per_tile=64)


@pytest.mark.slow
def test_loss_2d_is_zero_at_the_truth_and_grows_with_error(setup):
    heads, poses = setup
    data = training_set(heads[:1], poses, k=16, cache=False, progress=False)
    faces = padded_faces(heads[:1])[0]
    truth = data.displacements[0][jnp.asarray([poses.labels.index("jawOpen"), 0])]
    cameras = OPTS.cameras()

    def loss(predicted):
        return loss_2d(predicted, truth, data.vertices[0], faces, data.landmarks[0], cameras, OPTS)

    zero, terms = loss(truth)
    assert float(zero) == pytest.approx(0.0, abs=1e-6)
    small, _ = loss(truth * 0.8)
    large, terms = loss(truth * 0.0)
    assert 0.0 < float(small) < float(large)
    assert float(terms["flow"]) == pytest.approx(1.0, rel=1e-3)  # no motion: the target's scale
    grad = jax.grad(lambda p: loss(p)[0])(truth * 0.5)
    assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.abs(grad).max()) > 0


@pytest.mark.slow
def test_3d_loss_never_sees_an_unrigged_head(setup, tmp_path):
    """The unrigged head's 3D ground truth is NaN: stages "3d" and "3d+2d" (whose 2D term
    also draws from the rigged heads) stay finite; stage "2d" reads it (through renders)."""
    heads, poses = setup
    hidden = dataclasses.replace(
        heads[1], displacements=np.full_like(heads[1].displacements, np.nan)
    )
    data = training_set([heads[0], hidden], poses, k=16, cache=False, progress=False)
    faces = padded_faces([heads[0], hidden])
    options = RigAnyFaceTrainOptions(
        width=8,
        global_size=4,
        global_width=8,
        k=16,
        steps=2,
        warmup_steps=1,
        poses_per_step=2,
        log_every=1,
    )
    for stage in ("3d", "3d+2d"):
        _, step, _, history = train_2d(
            data,
            faces,
            poses,
            [0],
            options,
            OPTS,
            stage=stage,
            progress=False,
            checkpoint=tmp_path / f"{stage}.eqx",
        )
        assert step == 2 and all(np.isfinite(r["loss"]) for r in history)
        # resuming a finished run is a no-op with the same history
        _, again, _, history2 = train_2d(
            data,
            faces,
            poses,
            [0],
            options,
            OPTS,
            stage=stage,
            progress=False,
            checkpoint=tmp_path / f"{stage}.eqx",
        )
        assert again == 2 and history2 == history


def test_bad_input(setup):
    heads, poses = setup
    data = training_set(heads[:1], poses, k=16, cache=False, progress=False)
    options = RigAnyFaceTrainOptions(width=8, k=16, steps=2, warmup_steps=1, poses_per_step=2)
    faces = padded_faces(heads[:1])
    with pytest.raises(ValueError, match="stage"):
        train_2d(data, faces, poses, [0], options, OPTS, stage="3d-only")
    with pytest.raises(ValueError, match="rigged"):
        train_2d(data, faces, poses, [3], options, OPTS, stage="3d")
    with pytest.raises(ValueError, match="poses_2d"):
        train_2d(data, faces, poses, [0], options, Supervision2DOptions(poses_2d=4), stage="2d")
    with pytest.raises(ValueError, match="image_size"):
        Supervision2DOptions(image_size=2)
