"""RigAnyFace on ICT identities: train with and without the global encoder and as a
correction on top of deformation transfer (``raf_dt_residual``); evaluate against no motion,
copied ICT deltas and deformation transfer on held-out identities (by pose class and vertex
class, the worst poses) and on the MakeHuman hm08 head against its person-made ARKit targets
(evaluation only: nothing is trained or tuned on it).

    python experiments/autorig.py --out experiments/results/autorig            # standard
    python experiments/autorig.py --out /tmp/autorig --quick                   # tests

Every model is trained (or resumed: a finished checkpoint trains no further) with the recipe
of ``canrig_jax.papers.riganyface.recipe_options``, then evaluated. ``--residual-gate TAU``
gates the residual model's correction by the DT motion (``RigAnyFace(residual_gate=)``: what DT
leaves still stays still), ``--residual-static-weight`` sets its static-vertex term.
``--raf-loss`` (``papers.riganyface.RAF_LOSSES``), ``--raf-width`` and
``--raf-conditional-blocks`` set the pure models' loss and size. ``--anchor MODE`` adds a
second anchored-DT base (``transfer_poses(anchor=)``: "part", or "skin_vertex": per vertex on
the skin, per part elsewhere) and, with ``--anchored-residual``, its residual model
``raf_anchored_<mode>_dt_residual``.

The other questions have their own scripts, on checkpoints this one (or autorig_train.py)
made: ``autorig_train.py`` trains one model, ``autorig_validate.py`` compares checkpoints on
validation identities (how a model is chosen), ``autorig_evaluate.py`` evaluates checkpoints
trained outside the standard folder, ``autorig_placement.py``, ``autorig_penetration.py`` and
``autorig_timing.py`` re-measure one section of a results.json.

Writes DIR/results.json, DIR/table.md, DIR/training_loss.png, DIR/poses_<head>.png and
DIR/makehuman.png (predicted poses with 0-5 mm error maps next to the ground truth),
DIR/makehuman_shapes.png (each method's amount of motion per shape against the sculpted one),
DIR/rig.glb (one predicted rig as glTF 2.0 with named morph targets) and the checkpoints
(rerunning resumes from them). ``--cache DIR`` keeps the training heads' transferred poses
(the residual model's base) between runs.

MakeHuman protocol: the head is converted from decimetres to centimetres; the ICT face part
is fitted to it by a trimmed-ICP similarity (start: identity rotation, nose tips together),
which places ICT's 68 landmarks on its skin (nearest vertex); the correspondence is the
library's ``head_correspondence`` from those landmarks (no hand-picked vertices). The 51
ARKit shapes it shares with ICT are compared; ICT's ``browInnerUp_L/_R`` and
``cheekPuff_L/_R`` are summed.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import RigAnyFaceNetwork, ict_autorig_dataset
from canrig_jax.papers.riganyface import (
    ANCHOR_CM,
    ANCHOR_MODES,
    ANCHORED_RESIDUAL_MODELS,
    HELDOUT_SPLIT,
    PURE_MODELS,
    RESIDUAL_MODEL,
    STATIC_MM,
    add_recipe_arguments,
    anchored_base_key,
    autorig_table,
    class_errors,
    evaluate_makehuman,
    evaluate_splits,
    evaluation_rows,
    gltf_round_trip,
    makehuman_shapes,
    plot_pose_examples,
    plot_training_history,
    recipe_base,
    recipe_options,
    recipe_training_set,
    rig_timing,
    train_checkpoint,
    worst_poses,
)
from canrig_jax.watchdog import run_watched


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    add_recipe_arguments(parser)
    parser.add_argument("--test-identities", type=int, default=8)
    parser.add_argument(
        "--anchored-residual",
        action="store_true",
        help="also train (or resume) and evaluate raf_anchored_dt_residual: the residual "
        "model with the same recipe on anchored deformation transfer (its training and "
        "evaluation base)",
    )
    parser.add_argument(
        "--anchor",
        choices=ANCHOR_MODES,
        default="vertex",
        help="anchoring of a second anchored-DT base (transfer_poses(anchor=)) evaluated next "
        "to the per-vertex one; with --anchored-residual its residual model "
        "(raf_anchored_<mode>_dt_residual) is trained or resumed and evaluated too "
        "(default: %(default)s, only the per-vertex base)",
    )
    return parser.parse_args(argv)


def train_all(args, dataset, anchors) -> tuple[dict, dict]:
    """Train (or resume) the pure models and the residual models in ``args.out``: (name ->
    model, name -> its training record)."""
    progress = not args.no_progress
    k = recipe_options(args).k
    residuals = [RESIDUAL_MODEL] + [
        name
        for name, mode in ANCHORED_RESIDUAL_MODELS.items()
        if args.anchored_residual and mode in anchors
    ]
    models, trained = {}, {}
    data = None
    for name in (*PURE_MODELS, *residuals):
        if data is None or name not in PURE_MODELS:  # the pure models share their data
            data = None  # release the previous training set first
            data = recipe_training_set(
                dataset,
                name,
                k=k,
                cache=args.cache,
                seed=args.seed,
                progress=progress,
                options=recipe_options(args, name),
            )
            print(f"{name}: {len(dataset.train)} training heads, {data.vertices.shape[1]} v")
        path = args.out / f"checkpoint_{name}.eqx"
        options = recipe_options(args, name)
        models[name], trained[name] = train_checkpoint(
            path, data, dataset.poses, options, progress=progress, devices=args.devices
        )
        if recipe_base(name) is not None:
            trained[name]["base"] = recipe_base(name)
    return models, trained


def main(argv=None):
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    record_command(args.out, command)
    start = time.perf_counter()
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=2 if args.quick else args.train_identities,
        n_test=1 if args.quick else args.test_identities,
        seed=args.seed,
        progress=not args.no_progress,
    )
    poses, options = dataset.poses, recipe_options(args)
    anchors = ("vertex",) if args.anchor == "vertex" else ("vertex", args.anchor)
    models, trained = train_all(args, dataset, anchors)

    # -- evaluation on held-out heads, then MakeHuman hm08 (evaluation only) --------------
    rows = evaluation_rows(models)
    found = evaluate_splits(dataset, models, rows, anchors, k=options.k)
    predicted, truth = found["predictions"], found["truth"]
    makehuman, makehuman_info, makehuman_example = evaluate_makehuman(
        dataset, models, rows, args.data_dir, anchors
    )
    rig_seconds = rig_timing(models["raf"], poses, dataset.head)  # ~1,750 vertices
    head, _ = found["examples"][HELDOUT_SPLIT]
    exported = RigAnyFaceNetwork((models["raf"], poses)).generate(head.vertices, head.faces).rig
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
        "heldout": {name: class_errors(p, truth, poses) for name, p in predicted.items()},
        "heldout_protocol": {
            "split": HELDOUT_SPLIT,
            "anchored": f"deformation transfer with static_below = {ANCHOR_CM} cm "
            "(transfer_poses): per pose, vertices whose carried ICT displacement is shorter "
            "are held at zero; *_anchored rows use it as the residual model's base",
            "anchors": {
                anchored_base_key(m): f"transfer_poses(static_below={ANCHOR_CM}, anchor={m!r})"
                for m in anchors
            },
            "rows": {name: {"model": m, "base": b} for name, (m, b) in rows.items()},
            "heads": len(truth),
            "static_mm": STATIC_MM,
            "static": "a (pose, vertex) pair whose ground-truth displacement is < static_mm",
        },
        "worst_poses": {name: worst_poses(p, truth, poses, 5) for name, p in predicted.items()},
        "makehuman": makehuman,
        "makehuman_protocol": makehuman_info,
        "makehuman_shapes": makehuman_shapes(makehuman_example),
        "test": found["test"],
        "penetration": found["penetration"],
        "rig_seconds": rig_seconds,
        "parameters": {name: t["parameters"] for name, t in trained.items()},
        "training": {
            name: {k: v for k, v in t.items() if k != "history"} for name, t in trained.items()
        },
        "gltf": gltf_round_trip(exported, args.out / "rig.glb"),
        "total_minutes": (time.perf_counter() - start) / 60,
        "provenance": provenance(command),
    }
    save_json(args.out / "results.json", results)
    text = autorig_table(results)
    save_text(args.out / "table.md", text)
    print(text)
    plot_training_history(trained, args.out / "training_loss.png")
    plot_pose_examples(args.out, poses.labels, found["examples"], makehuman_example)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
