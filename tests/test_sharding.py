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
from canrig_jax import data_parallel_step, device_mesh, replicate, shard_batch
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


def test_two_devices_match_one():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["JAX_PLATFORMS"] = "cpu"
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert out["device_count"] == 2
    one, two = out["1"], out["2"]
    assert one["batch_devices"] == 1 and two["batch_devices"] == 2
    assert two["param_devices"] == 2  # parameters replicated on both devices
    np.testing.assert_allclose(two["losses"], one["losses"], rtol=1e-5)
    assert one["full_loss"] < out["start_loss"]  # it trains (loss on all 180 frames)
    assert two["full_loss"] == pytest.approx(one["full_loss"], rel=1e-5)
    assert "devices: 3 requested, 2 available" in out["error"]


def test_bad_batch_and_device_count():
    from canrig_jax import device_mesh, shard_batch

    mesh = device_mesh(1)
    with pytest.raises(ValueError, match="devices"):
        device_mesh(0)
    with pytest.raises(ValueError, match="batch: a leaf of shape"):
        shard_batch({"x": np.float32(1.0)}, mesh)
