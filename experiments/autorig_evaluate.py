"""Evaluate RigAnyFace checkpoints trained outside the standard folder (chosen beforehand on
validation identities, ``autorig_validate.py``) on the standard run's held-out test identities
and on the MakeHuman hm08 head, next to no motion, copied ICT deltas and deformation transfer
(plain and anchored). Nothing is trained.

    python experiments/autorig_evaluate.py --out experiments/results/autorig_long \\
        experiments/results/autorig_wide/checkpoint_raf.eqx \\
        experiments/results/autorig_long/checkpoint_raf.eqx

A checkpoint's row is named "<folder>/<file stem>"; a residual checkpoint is evaluated on
plain deformation transfer and on the anchored one ("+anchored_base"). On MakeHuman each model
is evaluated once more placed from its fitted face (``face_placement``). Penetration is
measured where the ground truth has none (``clean_penetration``).

Writes DIR/results.json (``heldout``, ``worst_poses``, ``heldout_shapes``, ``makehuman``,
``makehuman_shapes``, ``penetration_clean``, ``training``), DIR/table.md,
DIR/training_loss.png, DIR/poses_unseen_topology.png, DIR/heldout_shapes.png,
DIR/makehuman.png and DIR/makehuman_shapes.png.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.autorig import ict_autorig_dataset
from canrig_jax.papers.riganyface import (
    ANCHOR_CM,
    HELDOUT_SPLIT,
    STATIC_MM,
    autorig_table,
    checkpoint_record,
    class_errors,
    clean_penetration,
    evaluate_makehuman,
    evaluation_rows,
    heldout_predictions,
    heldout_shapes,
    load_checkpoint_rows,
    makehuman_shapes,
    plot_pose_examples,
    plot_shape_ratios,
    plot_training_history,
    worst_poses,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", metavar="CHECKPOINT")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--test-identities", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0, help="the standard run's seed")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    loaded = load_checkpoint_rows(args.checkpoints)
    models = {name: model for name, (model, _) in loaded.items()}
    training = {name: checkpoint_record(model, header) for name, (model, header) in loaded.items()}
    start = time.perf_counter()
    dataset = ict_autorig_dataset(  # held-out identities have their own random stream
        args.data_dir,
        n_train=1,
        n_test=args.test_identities,
        seed=args.seed,
        progress=not args.no_progress,
    )
    poses, heads = dataset.poses, dataset.test[HELDOUT_SPLIT]
    predicted, truth = heldout_predictions(dataset, models, ("vertex",), copy=True)
    makehuman, makehuman_info, makehuman_example = evaluate_makehuman(
        dataset, models, evaluation_rows(models), args.data_dir, face_placed=True
    )
    results = {
        "heldout": {name: class_errors(p, truth, poses) for name, p in predicted.items()},
        "heldout_protocol": {
            "identities": f"the standard run's held-out test identities (seed {args.seed})",
            "split": HELDOUT_SPLIT,
            "heads": len(truth),
            "static_mm": STATIC_MM,
            "static": "a (pose, vertex) pair whose ground-truth displacement is < static_mm",
            "anchored": f"deformation transfer with static_below = {ANCHOR_CM} cm",
        },
        "worst_poses": {name: worst_poses(p, truth, poses, 5) for name, p in predicted.items()},
        "heldout_shapes": heldout_shapes(heads, predicted, poses),
        "makehuman": makehuman,
        "makehuman_protocol": makehuman_info,
        "makehuman_shapes": makehuman_shapes(makehuman_example),
        **clean_penetration(heads, predicted, poses, dataset.head.part_names),
        "parameters": {name: t["parameters"] for name, t in training.items()},
        "training": {
            name: {k: v for k, v in t.items() if k != "history"} for name, t in training.items()
        },
        "total_minutes": (time.perf_counter() - start) / 60,
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    text = autorig_table(results)
    save_text(args.out / "table.md", text)
    print(text)
    plot_training_history(training, args.out / "training_loss.png")
    first = {name: p[0] for name, p in predicted.items() if name != "no_motion"}
    examples = {HELDOUT_SPLIT: (heads[0], first)}
    plot_pose_examples(args.out, poses.labels, examples, makehuman_example)
    plot_shape_ratios(
        results["heldout_shapes"],
        f"Held-out ICT identities ({len(heads)} heads, {HELDOUT_SPLIT})",
        args.out / "heldout_shapes.png",
    )
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
