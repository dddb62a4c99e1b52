"""Speed of RigAnyFace rig generation (issue 7, "Targets": <= 0.5 s for a ~1,750-vertex head).

    python benchmarks/bench_autorig.py [--checkpoint experiments/results/autorig/checkpoint_raf.eqx]
                                       [--repeats 5] [--out FILE]

The generic ICT head (all 17 parts) decimated to ~1,750 vertices; all 96 poses. Rows, one
process, median over ``--repeats``:

- **operators** (robust-laplacian L and M, 128 eigenpairs by shift-invert Lanczos, frames,
  gradients): what every new head costs before the network runs;
- **network, all poses, chunks of 16** (the library's ``generate_rig`` path: (V, 16, C)
  features through the conditional blocks, ``lax.map`` over 6 chunks), warm jit;
- **network, all poses in one pass** ((V, 96, C) features: the same function, activations
  too large for the CPU caches);
- **reference: one pose per call**, the same network called 96 times (what a per-pose
  DiffusionNet would cost);
- **generate_rig, warm** (a new head of similar size: operators + network + rig assembly).

Timing does not depend on the weights; without a checkpoint a freshly initialised model of
the standard configuration is timed. A Markdown table is printed (and written to ``--out``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from canrig_jax import save_text
from canrig_jax.autorig import (
    DEFAULT_POSE_CHUNK,
    TrainOptions,
    generate_rig,
    head_inputs,
    load_model,
    make_model,
    pad_to_bucket,
    predict_displacements,
    quartic_pose_set,
)
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.rig import ict_quartic_rig

DEFAULT_CHECKPOINT = Path(__file__).parents[1] / "experiments/results/autorig/checkpoint_raf.eqx"
TARGET_S = 0.5


def median_seconds(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    head = load_ict(args.data_dir, parts=None)
    if args.checkpoint.exists():
        model, poses, _ = load_model(args.checkpoint)
        source = f"trained ({args.checkpoint.name})"
    else:
        face_rig, _ = ict_quartic_rig(args.data_dir, progress=False)
        poses = quartic_pose_set(face_rig)
        model = make_model(TrainOptions(), poses.n_basis, 0.01)
        source = "untrained (no checkpoint; timing does not depend on weights)"
    meshes = [decimate(head.neutral, head.faces, n) for n in (1600, 1620)]
    mesh = meshes[0]
    vectors = jnp.asarray(poses.vectors())

    operators_s = median_seconds(
        lambda: head_inputs(mesh.vertices, mesh.faces, k=128, cache=False)[1].mass,
        args.repeats,
    )
    unit, operators, _, _ = head_inputs(mesh.vertices, mesh.faces, k=128, cache=False)
    padded = pad_to_bucket(operators, 256)
    unit_padded = jnp.zeros((padded.n_vertices, 3)).at[: unit.shape[0]].set(unit)
    chunk = DEFAULT_POSE_CHUNK
    predict_displacements(model, vectors, unit_padded, padded, chunk).block_until_ready()
    chunked_s = median_seconds(
        lambda: predict_displacements(model, vectors, unit_padded, padded, chunk), args.repeats
    )
    predict_displacements(model, vectors, unit_padded, padded).block_until_ready()
    batched_s = median_seconds(
        lambda: predict_displacements(model, vectors, unit_padded, padded), args.repeats
    )
    predict_displacements(model, vectors[:1], unit_padded, padded).block_until_ready()
    per_pose_s = median_seconds(
        lambda: [
            predict_displacements(model, vectors[p : p + 1], unit_padded, padded)
            for p in range(len(vectors))
        ][-1],
        max(1, args.repeats // 2),
    )
    generate_rig(model, poses, meshes[1].vertices, meshes[1].faces)  # compile this bucket
    warm_s = median_seconds(
        lambda: generate_rig(model, poses, mesh.vertices, mesh.faces).displacements,
        args.repeats,
    )

    rows = [
        f"# RigAnyFace rig generation: {mesh.n_vertices} vertices, {poses.n_poses} poses",
        "",
        f"model: {source}; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; median of "
        f"{args.repeats}",
        "",
        "| step | seconds | vs reference |",
        "|---|---|---|",
        f"| operators (L, M, 128 eigenpairs, gradients) | {operators_s:.3f} | |",
        f"| network, all poses, chunks of {chunk} | {chunked_s:.3f} | "
        f"{per_pose_s / chunked_s:.1f}x faster |",
        f"| network, all poses in one pass | {batched_s:.3f} | "
        f"{per_pose_s / batched_s:.1f}x faster |",
        f"| reference: network, one pose per call | {per_pose_s:.3f} | 1.0x |",
        f"| generate_rig (operators + network + rig), warm | {warm_s:.3f} | |",
        "",
        f"Target <= {TARGET_S} s: {'met' if warm_s <= TARGET_S else 'NOT met'} "
        f"(operators are {operators_s / warm_s:.0%} of it).",
    ]
    text = "\n".join(rows) + "\n"
    print(text)
    if args.out is not None:
        save_text(args.out, text)


if __name__ == "__main__":
    main()
