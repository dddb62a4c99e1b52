"""Steps per second of data-parallel training on 1 and 2 devices (host CPU devices).

    python benchmarks/bench_devices.py [--steps 40] [--batch 256] [--out FILE.md]

The step is ``canrig_jax._sharding.data_parallel_step`` on an MLP (52 ARKit weights -> 3 x 512 ICT
face-vertex displacements, width 256, depth 3) with batches drawn from the real Live Link
capture and the linear ICT rig; the batch is split over the devices, parameters replicated.
It runs in a subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=2``: on CPU
the two "devices" share the machine's cores, so this measures the sharding's overhead and
correctness, not a speed-up (which needs two accelerators or hosts). The 1-minute load
average is printed: the 2-core machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from canrig_jax._io import save_text

DEFAULT_OUT = Path(__file__).parent / "results" / "bench_devices.md"

WORKER = r"""
import json, sys, time
import equinox as eqx, jax, jax.numpy as jnp, numpy as np, optax
from canrig_jax._sharding import data_parallel_step, device_mesh, replicate, shard_batch
from canrig_jax.data import FACE, load_ict, load_livelinkface

steps, batch_size = int(sys.argv[1]), int(sys.argv[2])
capture, face = load_livelinkface(), load_ict(parts=FACE)
x = capture.weights.astype(np.float32)
w = capture.weights_for(face.names)
idx = np.linspace(0, face.neutral.shape[0] - 1, 512).astype(int)
y = np.einsum("tk,kvc->tvc", w, face.deltas[:, idx]).reshape(180, -1).astype(np.float32)
loss_fn = lambda m, b: jnp.mean((jax.vmap(m)(b["x"]) - b["y"]) ** 2)
rows = [np.random.default_rng(i).choice(180, batch_size) for i in range(steps + 3)]
out = {}
for n in (1, 2):
    mesh = device_mesh(n)
    model = eqx.nn.MLP(52, y.shape[1], 256, 3, key=jax.random.key(0))
    optimiser = optax.adam(1e-3)
    state = optimiser.init(eqx.filter(model, eqx.is_array))
    model, state = replicate((model, state), mesh)
    step = data_parallel_step(loss_fn, optimiser)
    batches = [shard_batch({"x": x[r], "y": y[r]}, mesh) for r in rows]
    for b in batches[:3]:  # compile and warm up
        model, state, loss = step(model, state, b)
    jax.block_until_ready(loss)
    start = time.perf_counter()
    for b in batches[3:]:
        model, state, loss = step(model, state, b)
    jax.block_until_ready(loss)
    out[n] = {"steps_per_second": steps / (time.perf_counter() - start), "loss": float(loss)}
print(json.dumps(out))
"""


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["JAX_PLATFORMS"] = "cpu"
    result = subprocess.run(
        [sys.executable, "-c", WORKER, str(args.steps), str(args.batch)],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    out = json.loads(result.stdout.strip().splitlines()[-1])
    load = os.getloadavg()[0]
    lines = [
        f"Data-parallel MLP step, batch {args.batch}, {args.steps} timed steps, "
        f"2 forced host devices on {os.cpu_count()} CPU cores, load average {load:.2f}",
        "",
        "| devices | steps / s | final loss |",
        "|---|---|---|",
    ]
    for n, row in out.items():
        lines.append(f"| {n} | {row['steps_per_second']:.1f} | {row['loss']:.6g} |")
    text = "\n".join(lines) + "\n"
    print(text)
    save_text(args.out, text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
