"""Patch blendshapes on the whole ICT head (issue 18, the parts that need no training): the
patch layout, the basis, how well PBS represents held-out shapes, and the global-blendshape
(GBS) rows of Table 5.

    python experiments/canrig_pbs.py --out experiments/results/canrig_pbs

Whole-head shapes: the linear ICT rig on all 26,719 vertices (its 53 expressions; the
ict-quartic correctives exist on the face part only) at the Live Link capture's first half and
400 random sparse poses (training: the basis is picked from them), held out: the capture's
second half and 100 random sparse poses of another seed (``canrig.held_out_poses``).
Writes results.json, table.md, patch_layout.png, pbs_error.png.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from canrig_jax import CM_TO_MM, experiment_command, provenance, save_json, save_text  # noqa: E402
from canrig_jax.autorig import head_rig  # noqa: E402
from canrig_jax.canrig import (  # noqa: E402
    PBS_MODELS,
    PBS_VARIANTS,
    PBSTrainOptions,
    build_pbs_training_set,
    fit_pbs,
    global_blendshape_fit,
    held_out_poses,
    load_pbs_model,
    parameter_count,
    patch_layout,
    pbs_basis,
    pbs_reconstruct,
    pbs_shape,
    seed_distances,
    split_capture,
    train_pbs,
)
from canrig_jax.data import load_ict, load_livelinkface  # noqa: E402
from canrig_jax.mesh import edge_graph, farthest_point_vertices  # noqa: E402
from canrig_jax.render import plot_vertex_scalar, save_figure  # noqa: E402
from canrig_jax.rig import evaluate_batch, ict_quartic_rig, random_sparse_poses  # noqa: E402

SKIN = ("Face", "Head and Neck")


def _timed(fn, repeats=10):
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


MODELS_DIR = "models"
EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM = 4.0, 1.0  # Table 5's masks (CANRig-PBS)
POOL_SIZE = 4096  # candidate handle vertices on the skin for training


def _parser():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument("--patches", type=int, default=457)
    parser.add_argument("--basis", type=int, default=19)
    parser.add_argument("--rings", type=int, default=3)
    parser.add_argument("--handles", type=int, default=265)
    parser.add_argument("--n-random", type=int, default=400)
    parser.add_argument("--quick", action="store_true", help="60 patches, 60 training poses")
    parser.add_argument(
        "--train",
        choices=PBS_MODELS,
        default=None,
        help="train this model into OUT/models/NAME/checkpoint.eqx (resumable) and stop",
    )
    parser.add_argument("--minutes", type=float, default=15.0, help="training budget")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--decay-start", type=int, default=0)
    parser.add_argument("--decay-steps", type=int, default=4000)
    parser.add_argument("--no-progress", action="store_true")
    return parser


def _whole_head(args):
    """The whole ICT head, its patch layout, training and held-out shapes, PBS basis."""
    model = load_ict(args.data_dir, parts=None)
    face_rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    rig = head_rig(face_rig, model)
    neutral = np.asarray(model.neutral, np.float32)
    faces = np.asarray(model.faces)
    motion = np.linalg.norm(model.deltas, axis=-1).max(axis=0)
    active = motion > 0  # every vertex some expression moves (not the eyeballs)
    parts = [
        name
        for name, (a, b) in zip(model.part_names, model.part_vertex_range, strict=True)
        if active[a:b].any()
    ]
    start = time.perf_counter()
    layout = patch_layout(neutral, faces, args.patches, rings=args.rings, active=active)
    layout_s = time.perf_counter() - start
    print(f"layout: {args.patches} patches over {active.sum()} vertices in {layout_s:.1f} s")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    capture_train, capture_test = split_capture(capture)
    rng = np.random.default_rng(0)
    train = np.concatenate(
        [capture_train, random_sparse_poses(rng, args.n_random, rig.names, n_active=(4, 10))]
    ).astype(np.float32)
    test = held_out_poses(capture_test, rig.names)
    train_shapes = np.asarray(evaluate_batch(rig, train, chunk=32), np.float32)
    test_shapes = np.asarray(evaluate_batch(rig, test, chunk=32), np.float32)
    basis, picked = pbs_basis(neutral, train_shapes, args.basis)
    skin = np.zeros(len(neutral), bool)
    for name, (a, b) in zip(model.part_names, model.part_vertex_range, strict=True):
        skin[a:b] |= name in SKIN
    return dict(
        model=model,
        rig=rig,
        neutral=neutral,
        faces=faces,
        active=active,
        parts=parts,
        layout=layout,
        layout_s=layout_s,
        capture=capture,
        capture_train=capture_train,
        train=train,
        test=test,
        train_shapes=train_shapes,
        test_shapes=test_shapes,
        basis=basis,
        picked=picked,
        skin=skin,
        graph=edge_graph(neutral, faces),
    )


def _training_set(args, head):
    pool = np.random.default_rng([0, 3]).choice(
        np.flatnonzero(head["skin"]), min(POOL_SIZE, int(head["skin"].sum())), replace=False
    )
    distances = seed_distances(head["layout"], head["graph"])
    return build_pbs_training_set(
        head["neutral"], head["train_shapes"], head["layout"], head["basis"], distances, pool
    ), distances


def _train(args, argv, head):
    options = PBSTrainOptions(
        model=args.train,
        steps=args.steps,
        max_minutes=args.minutes,
        decay_start=args.decay_start,
        decay_steps=args.decay_steps,
    )
    data, _ = _training_set(args, head)
    folder = args.out / MODELS_DIR / args.train
    folder.mkdir(parents=True, exist_ok=True)
    scale = float(np.abs(head["train_shapes"] - head["neutral"]).max())
    _, step, seconds, history = train_pbs(
        data,
        options,
        checkpoint=folder / "checkpoint.eqx",
        displacement_scale=scale,
        progress=not args.no_progress,
    )
    save_json(
        folder / "train.json",
        {
            "model": args.train,
            "steps": step,
            "train_minutes": seconds / 60,
            "options": options.to_dict(),
            "history": history,
            "provenance": provenance(experiment_command(__file__, argv)),
        },
    )
    print(f"{args.train}: {step} steps in {seconds / 60:.1f} min")


def main(argv=None):
    args = _parser().parse_args(argv)
    if args.quick:
        args.patches, args.n_random = 60, 60
    command = experiment_command(__file__, argv)
    head = _whole_head(args)
    if args.train is not None:
        return _train(args, argv, head)
    model, neutral, faces = head["model"], head["neutral"], head["faces"]
    layout, layout_s, parts = head["layout"], head["layout_s"], head["parts"]
    sizes = np.array([len(v) for v in layout.patch_vertices()])
    capture, capture_train = head["capture"], head["capture_train"]
    test, test_shapes = head["test"], head["test_shapes"]
    basis, picked, active = head["basis"], head["picked"], head["active"]

    fitted = fit_pbs(layout, neutral, basis, test_shapes)
    represented = np.asarray(pbs_shape(layout, neutral, basis, fitted))
    error = np.linalg.norm(represented - test_shapes, axis=-1) * CM_TO_MM  # (T, V) mm
    face = slice(*model.part_vertex_range[0])
    pbs = {
        "patches": args.patches,
        "basis": args.basis,
        "rings": args.rings,
        "parts": parts,
        "active_vertices": int(active.sum()),
        "patch_size": {
            "min": int(sizes.min()),
            "median": float(np.median(sizes)),
            "max": int(sizes.max()),
        },
        "max_patches_per_vertex": int(layout.vertex_patches.shape[1]),
        "basis_training_index": picked.tolist(),
        "fit_mean_mm": float(error.mean()),
        "fit_p95_mm": float(np.percentile(error, 95)),
        "fit_face_mean_mm": float(error[:, face].mean()),
        "fit_max_mm": float(error.max()),
        "layout_seconds": layout_s,
    }

    # Table 5, GBS rows: handles by geodesic farthest points on the skin (Face, Head and
    # Neck), reconstruction relative to the neutral (no base shape), error over every vertex
    skin = head["skin"]
    skin_index = np.flatnonzero(skin)
    local = np.full(len(neutral), -1)
    local[skin_index] = np.arange(len(skin_index))
    skin_faces = local[faces[skin[faces].all(axis=1)]]
    graph = edge_graph(neutral[skin_index], skin_faces)
    handles = skin_index[farthest_point_vertices(neutral[skin_index], args.handles, graph=graph)]
    offsets = test_shapes - neutral
    table5 = {}
    for name, shapes in (("gbs_pbs_basis", basis), ("gbs_ict_53", np.asarray(model.deltas))):
        weights = global_blendshape_fit(shapes, handles, offsets[:, handles])
        predicted = neutral + np.einsum("tb,bnk->tnk", np.asarray(weights), shapes)
        per_shape = (np.linalg.norm(predicted - test_shapes, axis=-1) * CM_TO_MM).mean(axis=1)
        table5[name] = {
            "mean_mm": float(per_shape.mean()),
            "std_mm": float(per_shape.std()),
            "train_minutes": 0.0,
            "basis_size": int(len(shapes)),
        }
    no_motion = (np.linalg.norm(offsets, axis=-1) * CM_TO_MM).mean(axis=1)
    table5["no_motion"] = {
        "mean_mm": float(no_motion.mean()),
        "std_mm": float(no_motion.std()),
        "train_minutes": 0.0,
    }

    # Table 5 and Figure 8, the trained rows: the same handles, base = the neutral
    data, distances = _training_set(args, head)
    handle_distance = jnp.asarray(distances[:, handles])
    trained, figure8, forward = {}, {}, {}
    for name in PBS_MODELS:
        checkpoint = args.out / MODELS_DIR / name / "checkpoint.eqx"
        if not checkpoint.exists():
            print(f"{name}: no checkpoint at {checkpoint}, row skipped")
            continue
        net, state = load_pbs_model(checkpoint, neutral, args.patches, len(basis))
        shapes = np.asarray(
            pbs_reconstruct(
                net,
                data,
                jnp.asarray(handles),
                handle_distance,
                jnp.asarray(neutral),
                jnp.asarray(test_shapes),
                EVAL_RADIUS_CM,
                EVAL_FALLOFF_PER_CM,
            )
        )
        per_shape = (np.linalg.norm(shapes - test_shapes, axis=-1) * CM_TO_MM).mean(axis=1)
        trained[name] = {
            "mean_mm": float(per_shape.mean()),
            "std_mm": float(per_shape.std()),
            "train_minutes": float(state["seconds"] / 60),
            "steps": int(state["step"]),
            "parameters": parameter_count(net),
        }
        if name in PBS_VARIANTS:
            figure8[name] = trained[name]["mean_mm"]
        print(f"{name}: {trained[name]}")
        # one whole-head forward pass at 200 handles (CANRig-PBS models)
        h200, d200 = jnp.asarray(handles[:200]), handle_distance[:, :200]
        one = jnp.asarray(test_shapes[:1])
        forward[name] = _timed(
            lambda net=net, h200=h200, d200=d200, one=one: pbs_reconstruct(
                net,
                data,
                h200,
                d200,
                jnp.asarray(neutral),
                one,
                EVAL_RADIUS_CM,
                EVAL_FALLOFF_PER_CM,
            )
        )
    table5.update(trained)

    # gather form against the sparse matrix product, one shape
    w_layout = layout.matrix()
    weights0 = jnp.asarray(fitted[0])
    basis_j = jnp.asarray(basis)
    neutral_j = jnp.asarray(neutral)
    gather_ms = _timed(lambda: pbs_shape(layout, neutral_j, basis_j, weights0))

    def sparse():
        per_vertex = w_layout @ np.asarray(weights0)  # (N, B)
        return neutral + np.einsum("nb,bnk->nk", per_vertex, basis)

    sparse_ms = _timed(sparse)
    timing = {"pbs_shape_gather_ms": gather_ms, "pbs_shape_scipy_sparse_ms": sparse_ms}
    print(
        f"PBS fit: mean {pbs['fit_mean_mm']:.4f} mm, p95 {pbs['fit_p95_mm']:.4f} mm; "
        f"gather {gather_ms:.2f} ms, scipy.sparse {sparse_ms:.2f} ms"
    )

    results = {
        "pbs": pbs,
        "table5": table5,
        "timing": timing,
        "protocol": {
            "shapes": "linear ICT rig, all 26,719 vertices",
            "train": f"capture frames 0-{len(capture_train) - 1} + {args.n_random} random poses",
            "test": f"capture frames {len(capture_train)}-{len(capture) - 1} + 100 random "
            "poses (held_out_poses)",
            "handles": f"{args.handles} geodesic farthest points on the skin ({', '.join(SKIN)})",
        },
        "not_built": "CANRig-PBS and Shape Transformer (training), Figure 8, Table 6",
        "provenance": provenance(command),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    rows = [
        "| method | mean (std) mm | training minutes |",
        "|---|---|---|",
    ]
    labels = {
        "no_motion": "no motion (the neutral)",
        "gbs_pbs_basis": f"GBS, the {len(basis)} PBS offsets",
        "gbs_ict_53": "GBS, ICT's 53 expressions",
    }
    for key, label in labels.items():
        row = table5[key]
        rows.append(f"| {label} | {row['mean_mm']:.3f} ({row['std_mm']:.3f}) | 0 |")
    text = "\n".join(
        [
            "# Patch blendshapes on the whole ICT head (issue 18)",
            "",
            f"Command: `{command}`",
            "",
            f"PBS: {args.patches} patches over {pbs['active_vertices']} vertices "
            f"({', '.join(parts)}), {args.rings} rings of overlap, basis = neutral + "
            f"{len(basis)} extreme training shapes.",
            "",
            "| PBS fit of held-out shapes | mean mm | p95 mm | face mean mm | max mm |",
            "|---|---|---|---|---|",
            f"| per-patch least squares | {pbs['fit_mean_mm']:.4f} | {pbs['fit_p95_mm']:.4f} | "
            f"{pbs['fit_face_mean_mm']:.4f} | {pbs['fit_max_mm']:.3f} |",
            "",
            f"Table 5 (GBS rows; {args.handles} handles, reconstruction relative to the neutral, "
            f"{len(test)} held-out shapes):",
            "",
            *rows,
            "",
            f"W_layout application: gather form {gather_ms:.2f} ms, "
            f"scipy.sparse {sparse_ms:.2f} ms (one shape).",
            "",
        ]
    )
    save_text(args.out / "table.md", text)
    save_text(args.out / "COMMAND", command + "\n")

    cell = np.asarray(layout.cell).astype(float)
    shuffled = np.random.default_rng(0).permutation(args.patches)
    colour = np.where(cell >= 0, shuffled[np.maximum(cell, 0).astype(int)], 0)
    fig, axes = plt.subplots(1, 2, figsize=(9, 5))
    for ax, view in zip(axes, ("front", "side"), strict=True):
        plot_vertex_scalar(
            ax,
            neutral,
            faces,
            colour,
            vmin=0,
            vmax=args.patches,
            cmap="tab20",
            view=view,
            title=f"{args.patches} patches ({view})",
        )
    save_figure(fig, args.out / "patch_layout.png")
    fig, ax = plt.subplots(figsize=(5, 5))
    plot_vertex_scalar(
        ax,
        neutral,
        faces,
        error.mean(axis=0),
        vmin=0,
        vmax=0.2,
        title="PBS fit, mean held-out error (0-0.2 mm)",
    )
    save_figure(fig, args.out / "pbs_error.png")


if __name__ == "__main__":
    main()
