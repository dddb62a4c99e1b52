"""Speed of WPSE training and run time (face and whole ICT head, 10 and 50 edits).

    python benchmarks/bench_wpse.py [--repeats 40] [--out benchmarks/results/bench_wpse.md]

Edits are synthetic (run time depends only on the edited vertex count and the number of
edits): at random sparse poses, a fraction of the blendshape offsets, on every vertex that
some blendshape moves by more than 1 micrometre. Run time is one frame per call of
``jax.jit(wpse.apply)`` given the posed base mesh (local frames included), against
``NumpyEditEvaluator`` (the same equations in NumPy) in the same process; also per frame of
``jax.vmap(wpse.apply)`` over all probe frames in one call (evaluating a whole take). The
1-minute load average is printed: the 2-core machine is shared, and timings scale with it.

A second table times the run time's distance product (S, K) x (K, P) alone, at P and at
``dot_width(P)`` (the padded width ``apply`` uses), alternating the two in one process.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax import wpse
from canrig_jax._io import save_text
from canrig_jax.papers.wpse import time_runtime
from canrig_jax.rig import evaluate_batch, ict_linear_rig, random_sparse_poses
from canrig_jax.wpse._metric import dot_width

DEFAULT_OUT = Path(__file__).parent / "results" / "bench_wpse.md"


def _fit(rig, poses, edits):
    model = wpse.fit_pose_space_edit(rig, poses, edits, sigma=0.15, support_tol=1e-4)
    return jax.block_until_ready(model)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    lines = [
        "| part | vertices (edited) | edits | train (s) | run time median / min (ms) "
        "| vmap over the frames (ms/frame) | NumPy median (ms) | load average |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for part, parts in (("face", "face"), ("head", None)):
        rig = ict_linear_rig(parts=parts) if parts is None else ict_linear_rig()
        probe = random_sparse_poses(rng, args.repeats, rig.names)
        posed = np.asarray(evaluate_batch(rig, probe))
        for n_edits in (10, 50):
            poses = random_sparse_poses(rng, n_edits, rig.names)
            scale = rng.uniform(-0.1, 0.1, (n_edits, rig.n_blendshapes, 1, 1))
            edits = (scale * np.asarray(rig.deltas)[None]).sum(axis=1).astype(np.float32)
            _fit(rig, poses, edits)
            start = time.perf_counter()
            model = _fit(rig, poses, edits)
            train = time.perf_counter() - start
            timed = time_runtime(model, probe, posed)
            times, numpy_times = timed["jax_seconds"], timed["numpy_seconds"]
            lines.append(
                f"| {part} | {rig.n_vertices} ({model.vertices.shape[0]}) | {n_edits} | "
                f"{train:.2f} | {1e3 * np.median(times):.2f} / {1e3 * np.min(times):.2f} | "
                f"{1e3 * timed['batched_seconds']:.2f} | "
                f"{1e3 * np.median(numpy_times):.2f} | {os.getloadavg()[0]:.1f} |"
            )
            print(lines[-1], flush=True)
    lines += ["", *_dot_widths(model.metric, args.repeats)]  # the head's, the last model
    table = "\n".join(lines) + "\n"
    save_text(args.out, table)
    print(table)
    print(f"wrote {args.out}")


def _dot_widths(metric, repeats: int) -> list[str]:
    """Table rows: ms per distance product at P columns and padded to ``dot_width(P)``."""
    rows = [
        f"Distance product ({metric.shape[0]} x {metric.shape[1]}) x ({metric.shape[1]} x P), "
        "median ms over alternating calls:",
        "",
        "| P | at P | at dot_width(P) | dot_width(P) |",
        "|---|---|---|---|",
    ]
    product = jax.jit(lambda m, d: m @ d.T)
    for p in (10, 20, 48, 50, 100):
        rng = np.random.default_rng(p)
        right = {
            w: jnp.asarray(rng.random((w, metric.shape[1]), np.float32)) for w in {p, dot_width(p)}
        }
        times = {w: [] for w in right}
        for d in right.values():
            jax.block_until_ready(product(metric, d))
        for _ in range(repeats):
            for w, d in right.items():
                start = time.perf_counter()
                jax.block_until_ready(product(metric, d))
                times[w].append(time.perf_counter() - start)
        padded = dot_width(p)
        rows.append(
            f"| {p} | {1e3 * np.median(times[p]):.2f} | {1e3 * np.median(times[padded]):.2f} "
            f"| {padded} |"
        )
        print(rows[-1], flush=True)
    return rows


if __name__ == "__main__":
    main()
