"""Speed of CANRig-PBS on the whole ICT head (issue 18): one call and batched frames.

    python benchmarks/bench_pbs.py [--checkpoint-dir DIR] [--handles 200] [--batch 16]
                                   [--repeats 20] [--out FILE]

26,719 vertices, 457 patches (3 rings), neutral + 18 basis offsets, 200 handles by farthest
points on the skin (Face, Head and Neck), Table 5's masks (radius 4 cm, falloff 1/cm) along the
mouth-attached graph, warm jit, float32, median over ``--repeats`` calls, all rows in one
process. Each row maps handle displacements to the whole-head shape (weights and
base + W_layout S_pred S_basis), with the patch queries and the patch means of the base cached
once per mesh, as a user's rig does:

- **CANRig-PBS + local prior** (the configuration that meets Table 5), **CANRig-PBS** (the
  paper's per-patch model), **Shape Transformer** and **the local PBS fit alone** (Cholesky
  factors of the fixed handles cached, one solve per edit);
- **reference: dense per-vertex CANRig** (an untrained ``ShapePreservingCANRig`` with the
  same encoder sizes, every one of the 26,719 vertices a query; masks along the same graph).

One call: a single edit. Batched: ``--batch`` edits through ``jax.vmap`` in one call, reported
per frame. The trained checkpoints of ``--checkpoint-dir`` (default
experiments/results/canrig_pbs_attached_local_prior) are used when present (they are not
committed); otherwise untrained models of the same sizes (speed does not depend on the
weights). Ratios are against the dense reference's one call, in the same run.

Target: CANRig-PBS forward <= 15 ms per call on 2 CPU cores (the paper: 23 ms, RTX 4090).
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax._io import save_text
from canrig_jax._timing import median_ms
from canrig_jax.canrig import CLAMP, ShapePreservingCANRig, influence_mask
from canrig_jax.data import load_ict
from canrig_jax.mesh import (
    attached_edge_graph,
    bridged_edge_graph,
    farthest_point_vertices,
    weighted_geodesic_distance,
)
from canrig_jax.pbs import (
    PBSTrainOptions,
    build_pbs_training_set,
    load_pbs_model,
    patch_layout,
    pbs_basis,
    seed_distances,
)
from canrig_jax.pbs._basis import local_fit_factor, local_fit_solve
from canrig_jax.pbs._model import patch_means, pbs_delta_shape
from canrig_jax.pbs._train import make_pbs_model, predict_pbs_weights
from canrig_jax.rig import evaluate_batch, ict_linear_rig, random_sparse_poses

DEFAULT_DIR = Path(__file__).parents[1] / "experiments/results/canrig_pbs_attached_local_prior"
RADIUS_CM, FALLOFF_PER_CM = 4.0, 1.0  # Table 5's masks
RIDGE = 0.011  # the local fit's ridge as canrig_pbs_attached_local_prior trained it
MOUTH_INTERIOR = ("Mouth socket", "Gums and tongue", "Teeth")
TARGET_MS = 15.0


def _head():
    model = load_ict(parts=None)
    rig = ict_linear_rig(parts=None)
    neutral, faces = np.asarray(rig.neutral, np.float32), np.asarray(rig.faces)
    moving = np.linalg.norm(np.asarray(rig.deltas), axis=-1).max(axis=0) > 0
    layout = patch_layout(neutral, faces, 457, rings=3, active=moving)
    poses = random_sparse_poses(np.random.default_rng(0), 60, rig.names)
    shapes = np.asarray(evaluate_batch(rig, poses), np.float32)
    basis, _ = pbs_basis(neutral, shapes, 19)
    interior, face = model.part_mask(MOUTH_INTERIOR), model.part_mask("Face")
    graph = attached_edge_graph(bridged_edge_graph(neutral, faces), neutral, interior, face)
    skin = np.flatnonzero(model.part_mask(["Face", "Head and Neck"]))
    return neutral, shapes, layout, basis, graph, skin


def _models(checkpoint_dir: Path, neutral, n_patches: int, n_weights: int):
    """{row name: model}, trained where ``checkpoint_dir`` holds the checkpoint."""
    rows = {
        "CANRig-PBS + local prior": ("per_patch", True),
        "CANRig-PBS (the paper's per-patch model)": ("per_patch", False),
        "Shape Transformer": ("shape_transformer", False),
    }
    checkpoints = {}  # kind -> the trained model, each checkpoint read once
    for kind in {kind for kind, _ in rows.values()}:
        path = checkpoint_dir / "models" / kind / "checkpoint.eqx"
        if path.exists():
            checkpoints[kind] = load_pbs_model(path, neutral, n_patches, n_weights)[0]
    models, trained = {}, []
    for name, (kind, prior) in rows.items():
        model = checkpoints.get(kind)
        if model is not None and getattr(model, "local_prior", False) == prior:
            trained.append(name)
        else:
            options = PBSTrainOptions(model=kind, local_prior=prior)
            model = make_pbs_model(options, neutral, n_patches, n_weights, 1.0)
        models[name] = model
    return models, trained


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint-dir", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--handles", type=int, default=200)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    neutral, shapes, layout, basis, graph, skin = _head()
    distances = seed_distances(layout, graph)
    data = build_pbs_training_set(neutral, shapes[:8], layout, basis, distances, skin[:64])
    handles = skin[farthest_point_vertices(neutral[skin], args.handles)]
    index, distance = jnp.asarray(handles), jnp.asarray(distances[:, handles])
    neutral_j, basis_j = jnp.asarray(neutral), jnp.asarray(basis)
    patch_base = patch_means(layout, neutral_j)
    # edits: held-out-like handle displacements of the random poses (cm)
    edits = jnp.asarray(shapes[-args.batch :, handles] - neutral[handles])
    models, trained = _models(args.checkpoint_dir, neutral, len(layout.seeds), len(basis))

    def network(model):
        queries = model.encode_patches(data.seeds)

        @eqx.filter_jit
        def one(model, d):
            weights = predict_pbs_weights(
                model, data, index, distance, neutral_j, d, RADIUS_CM, FALLOFF_PER_CM,
                queries=queries, patch_base=patch_base,
            )  # fmt: skip
            return pbs_delta_shape(layout, neutral_j, basis_j, weights)

        batched = eqx.filter_jit(jax.vmap(one, in_axes=(None, 0)))
        return lambda d: one(model, d), lambda ds: batched(model, ds)

    mask = influence_mask(distance, RADIUS_CM, FALLOFF_PER_CM, CLAMP)  # clamped, as the prior's
    handle_basis = basis_j[:, index]
    factors = local_fit_factor(handle_basis, mask, RIDGE)  # once per handle placement

    @jax.jit
    def local_one(d):
        weights = local_fit_solve(factors, handle_basis, mask, d)
        return pbs_delta_shape(layout, neutral_j, basis_j, weights)

    calls = {name: network(model) for name, model in models.items()}
    calls["local PBS fit alone (no network)"] = (local_one, jax.jit(jax.vmap(local_one)))

    # reference: the dense per-vertex CANRig on every vertex, masks along the same graph
    o = PBSTrainOptions()
    dense = ShapePreservingCANRig(
        neutral, n_heads=o.n_heads, latent=o.latent, width=o.width, n_layers=o.n_layers,
        fourier=o.fourier, key=jax.random.PRNGKey(0),
    )  # fmt: skip
    vertex_distance = weighted_geodesic_distance(graph.T.tocsr(), handles).T  # (V, H)
    vertex_mask = influence_mask(vertex_distance, RADIUS_CM, FALLOFF_PER_CM)
    dense_queries = dense.encode_queries(neutral_j)
    dense_call = eqx.filter_jit(
        lambda net, d: net(
            dense_queries, neutral_j, neutral_j[index], neutral_j[index], d, vertex_mask
        )  # fmt: skip
    )
    reference_ms = median_ms(lambda: dense_call(dense, edits[0]), max(3, args.repeats // 4))

    rows = []
    for name, (one, batched) in calls.items():
        single = np.asarray(one(edits[0]))
        stacked = np.asarray(batched(edits))
        if not (np.isfinite(stacked).all() and np.isfinite(single).all()):
            raise RuntimeError(f"{name}: non-finite output")
        same = float(np.abs(stacked[0] - single).max())
        one_ms = median_ms(lambda one=one: one(edits[0]), args.repeats)
        batch_ms = median_ms(lambda b=batched: b(edits), max(3, args.repeats // 4)) / args.batch
        rows.append((name, one_ms, batch_ms, same))

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"CANRig-PBS forward, whole ICT head ({len(neutral)} vertices, {len(layout.seeds)} "
        f"patches, {len(basis)} basis offsets), {len(handles)} skin handles, radius "
        f"{RADIUS_CM:g} cm, falloff {FALLOFF_PER_CM:g}/cm, mouth-attached graph, float32, warm "
        f"jit; one call: median of {args.repeats}; batched: {args.batch} edits through "
        "jax.vmap in one call, per edit",
        f"trained checkpoints ({args.checkpoint_dir.name}): {', '.join(trained) or 'none'}; "
        "the other rows untrained (speed does not depend on the weights)",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"load average {load:.1f} at the end, jax {jax.__version__}",
        "",
        "| model | one call ms | batched ms per edit | one call vs dense reference | "
        "batched vs its one call | batched[0] vs one call, max cm |",
        "|---|---|---|---|---|---|",
    ]
    for name, one_ms, batch_ms, same in rows:
        lines.append(
            f"| {name} | {one_ms:.1f} | {batch_ms:.1f} | {reference_ms / one_ms:.1f}x faster "
            f"| {one_ms / batch_ms:.1f}x | {same:.1e} |"
        )
    lines.append(
        f"| reference: dense per-vertex CANRig, {len(neutral)} queries | {reference_ms:.1f} "
        "| | 1.0x | | |"
    )
    ours = rows[0][1]
    lines += [
        "",
        f"target: CANRig-PBS + local prior <= {TARGET_MS:g} ms per call: "
        f"{'met' if ours <= TARGET_MS else 'not met'} ({ours:.1f} ms)",
    ]
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out is not None:
        save_text(args.out, table)
    return rows, reference_ms


if __name__ == "__main__":
    main()
