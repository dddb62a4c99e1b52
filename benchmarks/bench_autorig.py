"""Speed of RigAnyFace rig generation (issue 19: <= 1 s warm for a ~1,750-vertex head and 96
poses; issue 7: <= 0.5 s, for the width-32 model of its time).

    python benchmarks/bench_autorig.py [--checkpoint CKPT [CKPT ...]] [--repeats 5] [--out FILE]

The generic ICT head (all 17 parts) decimated to ~1,750 vertices; all 96 poses. Rows, one
process, median over ``--repeats``:

- **operators** (robust-laplacian L and M, 128 eigenpairs by shift-invert Lanczos, frames,
  gradients): what every new head costs before the network runs;
- **operators, from the disk cache** (the same head again, ``cache=`` a folder): against
  computing them;
- **orientation check** (``head_orientation``, the guard the network runs first): against
  the operators;
- **network, all poses, chunks of 16** (the library's ``RigAnyFaceNetwork.generate`` path:
  (V, 16, C) features through the conditional blocks, ``lax.map`` over 6 chunks), warm jit;
- **network, all poses in one pass** ((V, 96, C) features: the same function, activations
  too large for the CPU caches);
- **reference: one pose per call**, the same network called 96 times (what a per-pose
  DiffusionNet would cost);
- **generate_rig, warm** (``RigAnyFaceNetwork.generate`` of a new head of similar size:
  operators + network + rig assembly).

Each checkpoint is a column (default: the default model, ``autorig.DEFAULT_CHECKPOINT``, width
64, and the width-32 ``autorig`` one), timed in the same process on the same head. Timing does
not depend on the weights; a missing checkpoint is replaced by a freshly initialised width-32
model.
A Markdown table is printed (and written to ``--out``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from canrig_jax._checkpoint import parameter_count
from canrig_jax._io import save_text
from canrig_jax.autorig import (
    DEFAULT_CHECKPOINT,
    RigAnyFaceNetwork,
    RigAnyFaceTrainOptions,
    head_orientation,
    load_riganyface,
)
from canrig_jax.autorig._data import quartic_pose_set
from canrig_jax.autorig._rig import DEFAULT_POSE_CHUNK, pad_to_bucket, predict_displacements
from canrig_jax.autorig._train import head_inputs, make_model
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.rig import ict_quartic_rig

RESULTS = Path(__file__).parents[1] / "experiments" / "results"
DEFAULT_CHECKPOINTS = (
    DEFAULT_CHECKPOINT,  # the default model (issue 19)
    RESULTS / "autorig" / "checkpoint_raf.eqx",  # the width-32 model of issue 7
)
TARGETS_S = {"issue 19": 1.0, "issue 7, for the width-32 model": 0.5}


def median_seconds(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_model(model, poses, mesh, other, repeats: int) -> dict:
    """Seconds of each network row and of the warm ``RigAnyFaceNetwork.generate`` on ``mesh``
    (``other``: a second triangulation of similar size, which compiles the padding bucket)."""
    vectors = jnp.asarray(poses.vectors())
    unit, operators, _, _ = head_inputs(mesh.vertices, mesh.faces, k=128, cache=False)
    padded = pad_to_bucket(operators, 256)
    unit_padded = jnp.zeros((padded.n_vertices, 3)).at[: unit.shape[0]].set(unit)
    chunk = DEFAULT_POSE_CHUNK
    predict_displacements(model, vectors, unit_padded, padded, chunk).block_until_ready()
    chunked = median_seconds(
        lambda: predict_displacements(model, vectors, unit_padded, padded, chunk), repeats
    )
    predict_displacements(model, vectors, unit_padded, padded).block_until_ready()
    batched = median_seconds(
        lambda: predict_displacements(model, vectors, unit_padded, padded), repeats
    )
    predict_displacements(model, vectors[:1], unit_padded, padded).block_until_ready()
    per_pose = median_seconds(
        lambda: [
            predict_displacements(model, vectors[p : p + 1], unit_padded, padded)
            for p in range(len(vectors))
        ][-1],
        max(1, repeats // 2),
    )
    network = RigAnyFaceNetwork((model, poses))
    network.generate(other.vertices, other.faces)  # compile this bucket
    warm = median_seconds(
        lambda: network.generate(mesh.vertices, mesh.faces).displacements, repeats
    )
    return {"chunked": chunked, "batched": batched, "per_pose": per_pose, "warm": warm}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--checkpoint",
        type=Path,
        nargs="+",
        default=list(DEFAULT_CHECKPOINTS),
        help="checkpoints to time, side by side (default: the default model and the small one)",
    )
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    head = load_ict(args.data_dir, parts=None)
    models = {}
    for path in args.checkpoint:
        if path.exists():
            model, poses, _ = load_riganyface(path)
            name = f"{path.parent.name}/{path.name}"
        else:
            face_rig, _ = ict_quartic_rig(args.data_dir, progress=False)
            poses = quartic_pose_set(face_rig)
            model = make_model(RigAnyFaceTrainOptions(), poses.n_basis, 0.01)
            name = f"untrained width 32 ({path} missing; timing does not depend on weights)"
        models[f"{name}, {parameter_count(model):,} parameters"] = (model, poses)
    mesh, other = (decimate(head.neutral, head.faces, n) for n in (1600, 1620))
    operators_s = median_seconds(
        lambda: head_inputs(mesh.vertices, mesh.faces, k=128, cache=False)[1].mass,
        args.repeats,
    )
    with tempfile.TemporaryDirectory() as cache:
        head_inputs(mesh.vertices, mesh.faces, k=128, cache=cache)  # fills the cache
        cached_s = median_seconds(
            lambda: head_inputs(mesh.vertices, mesh.faces, k=128, cache=cache)[1].mass,
            args.repeats,
        )
    orientation_s = median_seconds(
        lambda: head_orientation(mesh.vertices, mesh.faces).margins, args.repeats
    )
    times = {name: time_model(*mp, mesh, other, args.repeats) for name, mp in models.items()}

    def cells(key, ratio=True):
        return " | ".join(
            f"{t[key]:.3f}" + (f" ({t['per_pose'] / t[key]:.1f}x faster)" if ratio else "")
            for t in times.values()
        )

    def same(seconds, reference, what):  # a model-independent row, as a ratio
        return " | ".join(f"{seconds:.3f} ({seconds / reference:.1%} {what})" for _ in times)

    rows = [
        f"# RigAnyFace rig generation: {mesh.n_vertices} vertices, {poses.n_poses} poses",
        "",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
        f"{os.getloadavg()[0]:.1f}; median of {args.repeats}; seconds (in brackets: against "
        "the same model called once per pose)",
        "",
        "| step | " + " | ".join(times) + " |",
        "|---|" + "---|" * len(times),
        "| operators (L, M, 128 eigenpairs, gradients) | "
        + " | ".join(f"{operators_s:.3f}" for _ in times)
        + " |",
        f"| operators, from the disk cache | {same(cached_s, operators_s, 'of computing')} |",
        f"| orientation check | {same(orientation_s, operators_s, 'of the operators')} |",
        f"| network, all poses, chunks of {DEFAULT_POSE_CHUNK} | {cells('chunked')} |",
        f"| network, all poses in one pass | {cells('batched')} |",
        f"| reference: network, one pose per call | {cells('per_pose', ratio=False)} |",
        f"| generate_rig (operators + network + rig), warm | {cells('warm', ratio=False)} |",
        "",
    ]
    for name, t in times.items():
        verdicts = ", ".join(
            f"<= {target} s ({issue}): {'met' if t['warm'] <= target else 'NOT met'}"
            for issue, target in TARGETS_S.items()
        )
        rows.append(f"- {name}: {verdicts} (operators are {operators_s / t['warm']:.0%} of it).")
    text = "\n".join(rows) + "\n"
    print(text)
    if args.out is not None:
        save_text(args.out, text)


if __name__ == "__main__":
    main()
