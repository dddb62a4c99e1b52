"""Speed of the CANRig forward pass and its workflows on the ICT face (issues 5 and 17).

    python benchmarks/bench_canrig.py [--checkpoint experiments/results/canrig/checkpoint.eqx]
                                      [--repeats 30] [--out FILE]

9,409 vertices, 200 handles, falloff 3/cm, warm jit, float32, median over ``--repeats``
calls, all rows in one process:

- **NeuralRig call** (the library's entry point): input validation in Python, the block
  layout on the host (which handles reach which vertex block), then the jitted forward
  pass ``deform`` with the block layout gathering around the one attention; radius 2, 1 and
  4 cm (the block width differs). Handles: geodesic farthest-point spread.
- **dense, cached queries**: ``deform`` with the dense layout.
- **reference: dense, uncached queries**: the same network with the queries of all 9,409
  vertices recomputed inside every call (the naive prototype).
- **pose A to B, direct / fitted** (``canrig.pose_a_to_b``), 200 random-vertex handles,
  2 cm: one call each (fitted: whitened Gauss-Newton with the Jacobian of the start, the
  default; Levenberg-Marquardt; and the exact Jacobian every step).
- **the rig with no network** (``canrig.LocalFitRig`` in a ``NeuralRig``, the configuration
  that ``experiments/canrig_workflows.py --rig local-fit`` selects: 600 patches, neutral + 59
  basis offsets from 400 random training poses, ridge 1e-4): ``pose_a_to_b`` direct, and
  fitted (``FitOptions()``: 3 LSMR iterations), the same handles and poses.
- **dialogue replacement**: 22 frames batched with ``jax.vmap`` (direct), 40 mouth handles,
  radius 1 cm, per frame.
- **handle placement**: the Dijkstra runs from 200 handles (once per placement, not per edit).

Targets: forward <= 20 ms; fitted A to B <= 150 ms; dialogue <= 30 ms per frame.
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
import numpy as np

from canrig_jax._io import save_text
from canrig_jax._timing import call_times_ms
from canrig_jax.canrig import (
    FitOptions,
    NeuralRig,
    ShapePreservingCANRig,
    dialogue_replacement,
    expression_region,
    interior_vertices,
    load_model,
    pose_a_to_b,
)
from canrig_jax.canrig._layout import DENSE
from canrig_jax.canrig._rig import deform
from canrig_jax.mesh import farthest_point_vertices
from canrig_jax.pbs import local_fit_rig, patch_layout, pbs_basis
from canrig_jax.rig import evaluate_batch, ict_linear_rig, random_sparse_poses

DEFAULT_CHECKPOINT = Path(__file__).parents[1] / "experiments/results/canrig/checkpoint.eqx"
TARGETS_MS = {"forward": 20.0, "fitted": 150.0, "dialogue": 30.0}


@eqx.filter_jit
def uncached_forward(model, canonical, edit):
    """Reference: queries recomputed from S_0 in every call, dense attention."""
    return deform(model, model.encode_queries(canonical), canonical, edit, DENSE)


def _time(fn, repeats):
    """(median, minimum) milliseconds after one warm-up call."""
    times = call_times_ms(fn, repeats)
    return statistics.median(times), min(times)


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
        source = f"trained ({args.checkpoint.parent.name}/{args.checkpoint.name})"
    else:
        model = ShapePreservingCANRig(neutral, key=jax.random.PRNGKey(0))
        source = "untrained (speed does not depend on the weights)"
    rig = NeuralRig(model, neutral, faces)
    index = farthest_point_vertices(neutral, args.handles, graph=rig.graph)
    start = time.perf_counter()
    handles = rig.handles(index)
    placement_ms = (time.perf_counter() - start) * 1e3
    h = handles.n_handles
    rng = np.random.default_rng(0)
    displacements = rng.normal(0, 0.3, (h, 3)).astype(np.float32)
    edit = rig.edit(handles, displacements, 2.0, 3.0)
    rows = [
        (
            f"NeuralRig call, block-sparse, radius {r:g} cm",
            _time(lambda r=r: rig(handles, displacements, r, 3.0), args.repeats),
        )
        for r in (2.0, 1.0, 4.0)
    ]
    rows += [
        ("dense, cached queries", _time(lambda: rig.deform(edit, DENSE), args.repeats)),
        (
            "reference: dense, uncached queries",
            _time(lambda: uncached_forward(model, rig.canonical, edit), args.repeats),
        ),
    ]
    same = float(
        np.abs(
            np.asarray(rig(handles, displacements, 2.0, 3.0))
            - np.asarray(uncached_forward(model, rig.canonical, edit))
        ).max()
    )
    reference_ms = rows[-1][1][0]

    # workflows on real poses: A, B two sparse ICT expressions
    poses = np.zeros((47, face.n_blendshapes), np.float32)
    for row in poses:
        active = rng.choice(face.n_blendshapes, 6, replace=False)
        row[active] = rng.uniform(0.1, 1.0, 6)
    shapes = np.asarray(evaluate_batch(face, poses))
    random_handles = rig.handles(rng.choice(rig.n_vertices, h, replace=False), limit=5.0)
    a, b = shapes[0], shapes[1]

    def a_to_b(fit, options=None):
        options = options or FitOptions()
        return pose_a_to_b(rig, random_handles, a, b, 2.0, 3.0, fit=fit, options=options).shape

    few = max(3, args.repeats // 6)
    direct_ms = _time(lambda: a_to_b(False), args.repeats)
    workflow_rows = [
        ("pose A to B, direct", direct_ms),
        ("pose A to B, fitted (Jacobian of the start)", _time(lambda: a_to_b(True), few)),
        (
            "pose A to B, fitted, Levenberg-Marquardt (4 steps)",
            _time(lambda: a_to_b(True, FitOptions(damped=True, max_steps=4)), few),
        ),
        (
            "pose A to B, fitted (exact Jacobian every step)",
            _time(lambda: a_to_b(True, FitOptions(exact_jacobian=True)), few),
        ),
    ]
    training = np.asarray(
        evaluate_batch(face, random_sparse_poses(np.random.default_rng(1), 400, face.names))
    )
    layout = patch_layout(neutral, faces, 600, rings=3)
    local = NeuralRig(
        local_fit_rig(layout, pbs_basis(neutral, training, 60)[0], ridge=1e-4), neutral, faces
    )
    for name, fit in (("direct", False), ("fitted, 3 LSMR iterations", True)):
        workflow_rows.append(
            (
                f"no network (LocalFitRig), pose A to B, {name}",
                _time(
                    lambda fit=fit: pose_a_to_b(
                        local, random_handles, a, b, 2.0, 3.0, fit=fit
                    ).shape.block_until_ready(),
                    few,
                ),
            )
        )
    mouth = expression_region(face)
    interior = interior_vertices(rig, mouth, 1.8)
    mouth_handles = rig.handles(interior[farthest_point_vertices(neutral[interior], 40)])
    n_frames = 22
    source_clip, target_clip = shapes[2 : 2 + n_frames], shapes[2 + n_frames : 2 + 2 * n_frames]
    batch_ms = _time(
        lambda: dialogue_replacement(rig, source_clip, target_clip, mouth_handles, 1.0, 3.0),
        few,
    )
    workflow_rows.append(
        (
            f"dialogue replacement, {n_frames} frames batched, per frame",
            tuple(x / n_frames for x in batch_ms),
        )
    )

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"CANRig forward, {rig.n_vertices} vertices, {h} handles (geodesic farthest points), "
        f"radius 2 cm, falloff 3/cm, float32, warm jit, median of {args.repeats}; model {source}",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"load average {load:.1f} at the end, jax {jax.__version__}",
        "",
        "| variant | median ms | min ms | vs dense uncached reference |",
        "|---|---|---|---|",
    ]
    for name, (median, best) in rows:
        lines.append(f"| {name} | {median:.1f} | {best:.1f} | {reference_ms / median:.2f}x |")
    lines.append(f"| handle placement (Dijkstra, once per placement) | {placement_ms:.0f} | | |")
    lines += [
        "",
        f"block-sparse vs reference: max difference {same:.2e} cm; forward target <= "
        f"{TARGETS_MS['forward']:g} ms: "
        f"{'met' if rows[0][1][0] <= TARGETS_MS['forward'] else 'not met'}",
        "",
        f"Workflows, {h} random-vertex handles, radius 2 cm (A, B: sparse ICT expressions); "
        f"median of {few} calls",
        "",
        "| workflow | median ms | min ms | vs direct A to B |",
        "|---|---|---|---|",
    ]
    for name, (median, best) in workflow_rows:
        lines.append(f"| {name} | {median:.1f} | {best:.1f} | {median / direct_ms[0]:.1f}x |")
    fitted_ms, dialogue_ms = workflow_rows[1][1][0], workflow_rows[-1][1][0]
    lines += [
        "",
        f"fitted target <= {TARGETS_MS['fitted']:g} ms: "
        f"{'met' if fitted_ms <= TARGETS_MS['fitted'] else 'not met'}; dialogue target <= "
        f"{TARGETS_MS['dialogue']:g} ms/frame: "
        f"{'met' if dialogue_ms <= TARGETS_MS['dialogue'] else 'not met'}",
    ]
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out is not None:
        save_text(args.out, table)
    return rows, workflow_rows


if __name__ == "__main__":
    main()
