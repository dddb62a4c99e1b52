"""Data-parallel training: 2 host devices follow the 1-device trajectory (subprocess, CPU)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

# A small model on real data: an MLP from the capture's 52 ARKit weights to the linear ICT
# rig's displacement of 64 face vertices (cm), batches of 32 frames drawn by step number.
SCRIPT = r"""
import json, sys
import equinox as eqx, jax, jax.numpy as jnp, numpy as np, optax
from canrig_jax._sharding import data_parallel_step, device_mesh, replicate, shard_batch
from canrig_jax.data import load_ict, load_livelinkface, FACE

capture = load_livelinkface()
face = load_ict(parts=FACE)
x = capture.weights.astype(np.float32)                                  # (180, 52)
w = capture.weights_for(face.names)                                     # (180, 53)
idx = np.linspace(0, face.neutral.shape[0] - 1, 64).astype(int)
y = np.einsum("tk,kvc->tvc", w, face.deltas[:, idx]).reshape(180, -1).astype(np.float32)

def loss_fn(model, batch):
    pred = jax.vmap(model)(batch["x"])
    return jnp.mean((pred - batch["y"]) ** 2)

out = {"device_count": jax.device_count()}
start = float(loss_fn(eqx.nn.MLP(52, y.shape[1], 64, 2, key=jax.random.key(0)),
                     {"x": jnp.asarray(x), "y": jnp.asarray(y)}))
out["start_loss"] = start
for n in (1, 2):
    mesh = device_mesh(n)
    model = eqx.nn.MLP(52, y.shape[1], 64, 2, key=jax.random.key(0))
    optimiser = optax.adam(3e-3)
    state = optimiser.init(eqx.filter(model, eqx.is_array))
    model, state = replicate((model, state), mesh)
    step = data_parallel_step(loss_fn, optimiser)
    losses, shards = [], None
    for i in range(6):
        rows = np.random.default_rng(i).choice(180, 32, replace=False)
        batch = shard_batch({"x": x[rows], "y": y[rows]}, mesh)
        shards = len(batch["x"].sharding.device_set)
        model, state, loss = step(model, state, batch)
        losses.append(float(loss))
    leaf = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))[0]
    full = float(loss_fn(model, {"x": jnp.asarray(x), "y": jnp.asarray(y)}))
    out[str(n)] = {"losses": losses, "batch_devices": shards, "full_loss": full,
                   "param_devices": len(leaf.sharding.device_set)}
try:
    device_mesh(3)
except ValueError as error:
    out["error"] = str(error)
print(json.dumps(out))
"""


def _on_two_host_devices(script: str, timeout: int) -> dict:
    """Run ``script`` in a fresh process with 2 forced CPU devices; its last line's JSON."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["JAX_PLATFORMS"] = "cpu"
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=timeout
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_two_devices_match_one():
    out = _on_two_host_devices(SCRIPT, 600)
    assert out["device_count"] == 2
    one, two = out["1"], out["2"]
    assert one["batch_devices"] == 1 and two["batch_devices"] == 2
    assert two["param_devices"] == 2  # parameters replicated on both devices
    np.testing.assert_allclose(two["losses"], one["losses"], rtol=1e-5)
    assert one["full_loss"] < out["start_loss"]  # it trains (loss on all 180 frames)
    assert two["full_loss"] == pytest.approx(one["full_loss"], rel=1e-5)
    assert "devices: 3 requested, 2 available" in out["error"]


def test_bad_batch_and_device_count():
    from canrig_jax._sharding import device_mesh, shard_batch

    mesh = device_mesh(1)
    with pytest.raises(ValueError, match="devices"):
        device_mesh(0)
    with pytest.raises(ValueError, match="batch: a leaf of shape"):
        shard_batch({"x": np.float32(1.0)}, mesh)


# The two trainers on real data, 1 and 2 devices from the same start: CANRig on a tiny
# ict-quartic training set (the capture's first frames), RigAnyFace on one decimated ICT
# identity. Their loss histories must agree to float tolerance.
TRAINERS = r"""
import dataclasses, json, warnings
import jax, numpy as np
from canrig_jax import canrig, autorig
from canrig_jax.autorig._data import head_rig, make_head, pose_displacements, quartic_pose_set
from canrig_jax.data import load_ict, load_livelinkface
from canrig_jax.papers.canrig import split_capture
from canrig_jax.rig import ict_quartic_rig

rig, _ = ict_quartic_rig(progress=False)
with warnings.catch_warnings():
    warnings.filterwarnings("ignore", category=UserWarning)
    capture = load_livelinkface().weights_for(rig.names, missing="zero")
capture_train, _ = split_capture(capture[:12])
data = canrig.build_training_set(rig, capture_train, n_random=6, n_pool=40, seed=0)
examples = canrig.ExampleOptions(batch=4, n_vertices=48, n_handles=(3, 12), handle_bucket=12)
options = canrig.TrainOptions(steps=3, log_every=1, examples=examples)
out = {"canrig": {}, "riganyface": {}}
for n in (1, 2):
    result = canrig.train(data, options, progress=False, devices=n)
    out["canrig"][str(n)] = [h["loss"] for h in result.history]

poses = quartic_pose_set(rig)
ict_head = load_ict(parts=None)
displacements = pose_displacements(head_rig(rig, ict_head), poses)
head = make_head(
    ict_head, displacements, np.random.default_rng(3).standard_normal(100), "decimate_600",
    name="decimate_600",
)
head_data = autorig.training_set([head], poses, k=32, progress=False)
raf = autorig.RigAnyFaceTrainOptions(
    width=8, global_size=4, global_width=8, k=32, steps=3, warmup_steps=1,
    poses_per_step=4, heads_per_step=2, log_every=1,
)
for n in (1, 2):
    result = autorig.train_riganyface(head_data, poses, raf, progress=False, devices=n)
    out["riganyface"][str(n)] = [h["loss"] for h in result.history]
try:
    odd = dataclasses.replace(options, examples=dataclasses.replace(examples, batch=3))
    canrig.train(data, odd, progress=False, devices=2)
except ValueError as error:
    out["error"] = str(error)
print(json.dumps(out))
"""


@pytest.mark.slow  # ~1-2 min: builds both training sets in a subprocess with 2 host devices
def test_trainers_on_two_devices_match_one():
    out = _on_two_host_devices(TRAINERS, 900)
    for trainer in ("canrig", "riganyface"):
        one, two = out[trainer]["1"], out[trainer]["2"]
        assert len(one) == len(two) == 3
        np.testing.assert_allclose(two, one, rtol=1e-4)
    assert "devices" in out["error"] and "examples.batch = 3" in out["error"]
