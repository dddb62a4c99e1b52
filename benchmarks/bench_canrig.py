"""Speed of the CANRig forward pass on the ICT face (issue 5, "Targets").

    python benchmarks/bench_canrig.py [--checkpoint experiments/results/canrig/checkpoint.eqx]
                                      [--repeats 30] [--out FILE]

9,409 vertices, 200 handles (geodesic farthest-point spread, as in the evaluation), medium
radius 2 cm, falloff 3/cm, warm jit, float32, median over ``--repeats`` calls. Rows, all in
one process:

- **NeuralRig call** (the library's entry point): input validation in Python, the count of
  handles per vertex block (one small device->host read), then the jitted block-sparse
  forward (``canrig/blocks.py``) with the queries of S_0 cached and the masks computed from
  the placed handles' distances in the jit (radius and falloff are run-time arrays). Also
  at the small and large radius (1 and 4 cm), where the block width differs.
- **dense, cached queries**: ``deform``, the dense (V x H) attention, queries cached.
- **reference: dense, uncached queries**: the same network with the queries of all 9,409
  vertices recomputed inside every call (the naive prototype of the issue).
- **handle placement**: the Dijkstra runs from 200 handles (once per placement, not per edit).

Target: <= 20 ms on this CPU. A Markdown table is printed (and written to ``--out``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax.canrig import (
    NeuralRig,
    ShapePreservingCANRig,
    deform,
    farthest_point_vertices,
    load_model,
)
from canrig_jax.io import save_text
from canrig_jax.rig import ict_linear_rig

DEFAULT_CHECKPOINT = Path(__file__).parents[1] / "experiments/results/canrig/checkpoint.eqx"
TARGET_MS = 20.0


@eqx.filter_jit
def uncached_forward(model, canonical, handle_index, distance, displacements, radius, falloff):
    """Reference: queries recomputed from S_0 in every call."""
    queries = model.encode_queries(canonical)
    return deform(
        model,
        queries,
        canonical,
        canonical,
        handle_index,
        distance,
        displacements,
        radius,
        falloff,
        jnp.asarray(0.0, jnp.float32),
    )


def _time(fn, repeats):
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3, min(times) * 1e3


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT)
    parser.add_argument("--handles", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    face = ict_linear_rig()
    neutral, faces = np.asarray(face.neutral, np.float32), np.asarray(face.faces)
    if args.checkpoint.exists():
        model, _ = load_model(args.checkpoint, neutral)
        source = f"trained ({args.checkpoint.name})"
    else:
        model = ShapePreservingCANRig(neutral, key=jax.random.PRNGKey(0))
        source = "untrained (speed does not depend on the weights)"
    rig = NeuralRig(model, neutral, faces)
    index = farthest_point_vertices(neutral, args.handles, graph=rig.graph)
    start = time.perf_counter()
    handles = rig.handles(index)
    placement_ms = (time.perf_counter() - start) * 1e3
    h = handles.n_handles
    displacements = np.random.default_rng(0).normal(0, 0.3, (h, 3)).astype(np.float32)
    radius, falloff = np.full(h, 2.0, np.float32), np.full(h, 3.0, np.float32)
    args_dev = (
        jnp.asarray(handles.index),
        handles.distance,
        jnp.asarray(displacements),
        jnp.asarray(radius),
        jnp.asarray(falloff),
    )
    rows = [
        (
            f"NeuralRig call, block-sparse, radius {r:g} cm",
            _time(lambda r=r: rig(handles, displacements, r, 3.0), args.repeats),
        )
        for r in (2.0, 1.0, 4.0)
    ]
    rows += [
        (
            "dense, cached queries (deform)",
            _time(
                lambda: deform(
                    model,
                    rig.queries,
                    rig.canonical,
                    rig.canonical,
                    args_dev[0],
                    args_dev[1],
                    *args_dev[2:],
                    jnp.asarray(0.0, jnp.float32),
                ),
                args.repeats,
            ),
        ),
        (
            "reference: dense, uncached queries",
            _time(lambda: uncached_forward(model, rig.canonical, *args_dev), args.repeats),
        ),
    ]
    same = np.allclose(
        np.asarray(rig(handles, displacements, 2.0, 3.0)),
        np.asarray(uncached_forward(model, rig.canonical, *args_dev)),
        atol=1e-5,
    )
    reference_ms = rows[-1][1][0]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"CANRig forward, {rig.n_vertices} vertices, {h} handles, radius 2 cm, falloff 3/cm, "
        f"float32, warm jit, median of {args.repeats}; model {source}",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"load average {load:.1f} at the end, jax {jax.__version__}",
        "",
        "| variant | median ms | min ms | vs reference |",
        "|---|---|---|---|",
    ]
    for name, (median, best) in rows:
        lines.append(f"| {name} | {median:.1f} | {best:.1f} | {reference_ms / median:.2f}x |")
    lines.append(f"| handle placement (Dijkstra, once per placement) | {placement_ms:.0f} | | |")
    lines += [
        "",
        f"outputs agree with the reference: {same}; target <= {TARGET_MS:g} ms: "
        f"{'met' if rows[0][1][0] <= TARGET_MS else 'not met'}",
    ]
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out is not None:
        save_text(args.out, table)
    return rows


if __name__ == "__main__":
    main()
