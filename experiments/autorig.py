"""RigAnyFace on ICT identities: train with and without the global encoder, evaluate against
deformation transfer on held-out identities of seen and unseen triangulations.

    python experiments/autorig.py --out experiments/results/autorig            # standard
    python experiments/autorig.py --out /tmp/autorig --quick                   # tests
    python experiments/autorig.py --out experiments/results/autorig --timing-only

``--timing-only`` re-measures only the rig generation time (``rig_seconds``) of an existing
results.json with its RAF checkpoint and re-renders table.md.

Writes DIR/results.json, DIR/table.md, DIR/training_loss.png, DIR/poses_<head>.png (predicted
poses with 0-5 mm error maps next to the ground truth), DIR/rig.glb (one predicted rig as
glTF 2.0 with named morph targets) and the two checkpoints (rerunning resumes from them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax import CM_TO_MM, COMMAND_FILE, experiment_command, provenance, save_json, save_text
from canrig_jax.autorig import (
    TrainOptions,
    error_stats,
    generate_rig,
    head_inputs,
    ict_autorig_dataset,
    load_model,
    penetration,
    train,
    training_set,
    transfer_poses,
)
from canrig_jax.canrig import parameter_count
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import export_gltf, load_gltf_rig

MODELS = {"raf": {}, "raf_no_global_encoder": {"global_size": 0}}
SPLITS = ("same_topology", "unseen_topology")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="2 identities, 20 steps (tests)")
    parser.add_argument("--minutes", type=float, default=25.0, help="training budget per model")
    parser.add_argument("--steps", type=int, default=2500, help="step budget per model")
    parser.add_argument("--train-identities", type=int, default=24)
    parser.add_argument("--test-identities", type=int, default=8)
    parser.add_argument("--learning-rate", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--timing-only",
        action="store_true",
        help="re-measure only rig_seconds of --out/results.json with its RAF checkpoint",
    )
    args = parser.parse_args(argv)
    if args.timing_only:
        return refresh_timing(args, argv)
    progress = not args.no_progress
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    save_text(args.out / COMMAND_FILE, command + "\n")

    start = time.perf_counter()
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=2 if args.quick else args.train_identities,
        n_test=1 if args.quick else args.test_identities,
        seed=args.seed,
        progress=progress,
    )
    poses = dataset.poses
    options = TrainOptions(
        steps=20 if args.quick else args.steps,
        warmup_steps=5 if args.quick else 200,
        max_minutes=None if args.quick else args.minutes,
        learning_rate=args.learning_rate,
        seed=args.seed,
        checkpoint_every=10 if args.quick else 200,
    )
    data = training_set(dataset.train, poses, k=options.k, progress=progress)
    print(
        f"{len(dataset.train)} training heads ({data.vertices.shape[1]} padded vertices), "
        f"{poses.n_poses} poses, data in {time.perf_counter() - start:.0f} s"
    )

    # -- training (resumes from the checkpoints) ----------------------------------------------
    models, trained = {}, {}
    for name, overrides in MODELS.items():
        model_options = dataclasses.replace(options, **overrides)
        path = args.out / f"checkpoint_{name}.eqx"
        result = train(data, poses, model_options, checkpoint=path, progress=progress)
        models[name], _, state = load_model(path)
        trained[name] = {
            "steps": result.step,
            "minutes": result.seconds / 60,
            "parameters": parameter_count(models[name]),
            "final_train_error_mm": state["history"][-1]["error_mm"],
            "history": state["history"],
        }
        print(f"{name}: {result.step} steps in {result.seconds / 60:.1f} min")
    del data

    # -- evaluation on held-out heads ------------------------------------------------------------
    part_names = dataset.head.part_names
    test: dict = {name: {} for name in (*MODELS, "deformation_transfer")}
    pen: dict = {name: [] for name in (*MODELS, "ground_truth")}
    examples = {}
    for split in SPLITS:
        truth_all, unit_scale = [], []
        predicted_all = {name: [] for name in test}
        for head in dataset.test[split]:
            unit, operators, _, scale = head_inputs(head.vertices, head.faces, k=options.k)
            truth_all.append(head.displacements)
            unit_scale.append(scale)
            for name, model in models.items():
                generated = generate_rig(
                    model, poses, head.vertices, head.faces, operators=operators
                )
                predicted_all[name].append(generated.displacements)
                pen[name].append(penetration(head, generated.displacements, part_names))
            predicted_all["deformation_transfer"].append(transfer_poses(dataset, head))
            pen["ground_truth"].append(penetration(head, head.displacements, part_names))
            examples.setdefault(split, (head, {n: p[-1] for n, p in predicted_all.items()}))
            print(f"evaluated {head.name}")
        for name, predictions in predicted_all.items():
            stats = error_stats(np.concatenate(predictions, 1), np.concatenate(truth_all, 1))
            unit = error_stats(
                np.concatenate([p / s for p, s in zip(predictions, unit_scale, strict=True)], 1),
                np.concatenate([t / s for t, s in zip(truth_all, unit_scale, strict=True)], 1),
                scale=100.0,  # unit-sphere units x 1000 (error_stats multiplies by CM_TO_MM)
            )
            test[name][split] = {
                **stats,
                "mae_unit_sphere_x1000": unit["mae_mm"],
                "q95_unit_sphere_x1000": unit["q95_mm"],
                "heads": len(predictions),
            }

    # -- rig generation time, ~1,750 vertices -------------------------------------------------
    model = models["raf"]
    rig_seconds = rig_timing(model, poses, dataset.head)

    # -- glTF export of one predicted rig, reloaded with trimesh --------------------------------
    head, _ = examples["unseen_topology"]
    exported = generate_rig(model, poses, head.vertices, head.faces).rig
    export_gltf(exported, args.out / "rig.glb")
    reloaded = load_gltf_rig(args.out / "rig.glb")
    gltf_check = {
        "file": "rig.glb",
        "morph_targets": len(reloaded.names)
        + sum(c.indices.shape[0] for c in reloaded.correctives),
        "max_abs_difference_cm": float(
            max(
                np.abs(np.asarray(reloaded.neutral) - np.asarray(exported.neutral)).max(),
                np.abs(np.asarray(reloaded.deltas) - np.asarray(exported.deltas)).max(),
                *(
                    np.abs(
                        np.asarray(a.to_dense(exported.n_vertices))
                        - np.asarray(b.to_dense(exported.n_vertices))
                    ).max()
                    for a, b in zip(reloaded.correctives, exported.correctives, strict=True)
                ),
            )
        ),
        "names_equal": tuple(reloaded.names) == tuple(exported.names),
        "faces_equal": bool(np.array_equal(np.asarray(reloaded.faces), np.asarray(exported.faces))),
    }

    results = {
        "config": {
            "quick": args.quick,
            "train_heads": len(dataset.train),
            "train_identities": len(dataset.train) // 2,
            "test_identities": len(dataset.test["unseen_topology"]),
            "train_topologies": sorted({h.topology for h in dataset.train}),
            "same_topology": dataset.test["same_topology"][0].topology,
            "unseen_topology": dataset.test["unseen_topology"][0].topology,
            "poses": {
                "total": poses.n_poses,
                "single": poses.n_basis,
                "labels": list(poses.labels),
            },
            "options": options.to_dict(),
        },
        "test": test,
        "penetration": {name: float(np.mean(v)) for name, v in pen.items()},
        "rig_seconds": rig_seconds,
        "parameters": {name: t["parameters"] for name, t in trained.items()},
        "training": {
            name: {k: v for k, v in t.items() if k != "history"} for name, t in trained.items()
        },
        "gltf": gltf_check,
        "total_minutes": (time.perf_counter() - start) / 60,
        "provenance": provenance(command),
    }
    write_results(args.out, results)
    plot_history(trained, args.out / "training_loss.png")
    for split, (head, predictions) in examples.items():
        plot_poses(head, predictions, poses, args.out / f"poses_{split}.png")


def rig_timing(model, poses, head, repeats: int = 9) -> dict:
    """Seconds to generate the rig of the generic ICT head decimated to ~1,750 vertices:
    cold (first call: compile + operators + network) and warm (median over ``repeats``
    calls, alternating two triangulations of similar size so no operator is reused)."""
    timing_head = decimate(head.neutral, head.faces, 1600)
    timing_other = decimate(head.neutral, head.faces, 1620)
    cold = generate_rig(model, poses, timing_head.vertices, timing_head.faces)  # compile + ops
    warm = [
        generate_rig(model, poses, mesh.vertices, mesh.faces).seconds
        for mesh in [timing_other, timing_head] * (repeats // 2) + [timing_head]
    ]
    return {
        "vertices": timing_head.n_vertices,
        "poses": poses.n_poses,
        "cold": cold.seconds["total"],
        "warm": float(np.median([w["total"] for w in warm])),
        "warm_operators": float(np.median([w["operators"] for w in warm])),
        "warm_network": float(np.median([w["network"] for w in warm])),
        "warm_repeats": len(warm),
    }


def refresh_timing(args, argv=None) -> dict:
    """Re-measure ``rig_seconds`` of an existing results.json in ``args.out`` with its RAF
    checkpoint (the rest of the file is kept)."""
    path = args.out / "results.json"
    checkpoint = args.out / "checkpoint_raf.eqx"
    if not path.exists() or not checkpoint.exists():
        raise ValueError(
            f"--timing-only: needs results.json and checkpoint_raf.eqx in {args.out}; "
            "run without --timing-only first"
        )
    results = json.loads(path.read_text())
    model, poses, _ = load_model(checkpoint)
    results["rig_seconds"] = rig_timing(model, poses, load_ict(args.data_dir, parts=None))
    results["timing_provenance"] = provenance(experiment_command(__file__, argv))
    write_results(args.out, results)
    print(f"rewrote rig_seconds of {path} and table.md")
    return results


def write_results(out: Path, results: dict) -> None:
    """results.json and table.md in ``out`` (atomic), and the table on stdout."""
    save_json(out / "results.json", results)
    text = table(results)
    save_text(out / "table.md", text)
    print(text)


def table(r: dict) -> str:
    rows = [
        "## Table 1 analog: held-out identities, vertex error in mm",
        "",
        "ICT cm -> mm; in brackets the same on heads normalised to the unit sphere, x 1000.",
        "",
        "| method | same topology MAE | same Q95 | unseen topology MAE | unseen Q95 |",
        "|---|---|---|---|---|",
    ]
    for name, splits in r["test"].items():
        s, u = splits["same_topology"], splits["unseen_topology"]
        rows.append(
            f"| {name} | {s['mae_mm']:.3f} ({s['mae_unit_sphere_x1000']:.3f}) | "
            f"{s['q95_mm']:.3f} ({s['q95_unit_sphere_x1000']:.3f}) | "
            f"{u['mae_mm']:.3f} ({u['mae_unit_sphere_x1000']:.3f}) | "
            f"{u['q95_mm']:.3f} ({u['q95_unit_sphere_x1000']:.3f}) |"
        )
    rows += [
        "",
        "## Table 2 analog: penetration",
        "",
        "Fraction of teeth, gums and eyeball vertices outside the skin (winding number < 1/2),",
        "mean over poses and held-out heads.",
        "",
        "| | fraction |",
        "|---|---|",
    ]
    rows += [f"| {name} | {value:.4f} |" for name, value in r["penetration"].items()]
    t = r["rig_seconds"]
    head = f"{t['vertices']} vertices, {t['poses']} poses"
    rows += [
        "",
        "## Table 3 analog: rig generation and size",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| rig generation ({head}), cold: compile + operators + network (s) | {t['cold']:.2f} |",
        f"| warm, a new head of similar size: operators + network (s) | {t['warm']:.2f} "
        f"({t['warm_operators']:.2f} + {t['warm_network']:.2f}) |",
    ]
    rows += [f"| parameters {name} | {n:,} |" for name, n in r["parameters"].items()]
    rows += [
        f"| training {name}: steps / minutes / final batch error (mm) | {t['steps']} / "
        f"{t['minutes']:.1f} / {t['final_train_error_mm']:.3f} |"
        for name, t in r["training"].items()
    ]
    g = r["gltf"]
    rows += [
        f"| glTF export: morph targets / max abs difference after reload (cm) | "
        f"{g['morph_targets']} / {g['max_abs_difference_cm']:.2e} |"
    ]
    return "\n".join(rows) + "\n"


def plot_history(trained: dict, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, t in trained.items():
        steps = [h["step"] for h in t["history"]]
        ax.plot(steps, [h["error_mm"] for h in t["history"]], label=name, lw=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("training batch mean vertex error (mm)")
    ax.set_yscale("log")
    ax.legend()
    save_figure(fig, path)


def plot_poses(head, predictions: dict, poses, path: Path, n_poses: int = 4) -> None:
    """Ground truth and each method's prediction for the poses that move most, coloured by
    error (0-5 mm; ground truth coloured by displacement)."""
    size = np.linalg.norm(head.displacements, axis=-1).mean(axis=1)
    chosen = np.argsort(-size)[:n_poses]
    columns = ["ground_truth", *predictions]
    fig, axes = plt.subplots(n_poses, len(columns), figsize=(3 * len(columns), 3.2 * n_poses))
    skin = head.parts <= 1
    faces = head.faces[skin[head.faces].all(axis=1)]
    for row, p in enumerate(chosen):
        for col, name in enumerate(columns):
            displaced = head.displacements[p] if name == "ground_truth" else predictions[name][p]
            if name == "ground_truth":
                values = np.linalg.norm(head.displacements[p], axis=-1) * CM_TO_MM
            else:
                values = np.linalg.norm(displaced - head.displacements[p], axis=-1) * CM_TO_MM
            mappable = plot_vertex_scalar(
                axes[row, col],
                head.vertices + displaced,
                faces,
                values,
                vmax=5.0,
                title=f"{name}\n{poses.labels[p]}" if row == 0 or col == 0 else None,
            )
    fig.colorbar(
        mappable, ax=axes, shrink=0.5, label="mm (ground truth: displacement; others: error)"
    )
    save_figure(fig, path)


if __name__ == "__main__":
    main()
