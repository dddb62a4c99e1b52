"""RigAnyFace on ICT identities: train with and without the global encoder and as a
correction on top of deformation transfer (``raf_dt_residual``); evaluate against no motion,
copied ICT deltas and deformation transfer on held-out identities (by pose class and vertex
class, the worst poses) and on the MakeHuman hm08 head against its person-made ARKit targets
(evaluation only: nothing is trained or tuned on it).

    python experiments/autorig.py --out experiments/results/autorig            # standard
    python experiments/autorig.py --out /tmp/autorig --quick                   # tests
    python experiments/autorig.py --out experiments/results/autorig --timing-only

``--timing-only`` re-measures only the rig generation time (``rig_seconds``) of an existing
results.json with its RAF checkpoint and re-renders table.md. ``--penetration-only`` trains
nothing and builds no training data: with the committed checkpoints it measures, on the
held-out heads, penetration where the ground truth has none (``penetration_clean``:
``penetration_free_set``) and re-measures the plain penetration next to it.

``--train-only NAME`` trains (or resumes) one model's checkpoint (``raf_dt_residual`` too) and
writes no results: a chunk of a long run, or models in parallel processes; the standard command
then resumes the finished checkpoints and evaluates. ``--residual-gate TAU`` gates the residual
model's correction by the DT motion (``RigAnyFace(residual_gate=)``: what DT leaves still stays
still), ``--residual-static-weight`` sets its static-vertex term. ``--validation-only CKPT...``
compares checkpoints on validation identities (neither training nor test; how a model is
chosen) into DIR/validation.json. ``--raf-loss euclidean_static`` trains the pure
models with the per-vertex Euclidean loss plus the static-vertex term (issue 19; the run in
experiments/results/autorig_retrain) instead of the issue-7 squared loss. ``--anchor MODE``
adds a second anchored-DT base (``transfer_poses(anchor=)``: "part", or "skin_vertex": per
vertex on the skin, per part elsewhere) and, with ``--anchored-residual``, its residual model
``raf_anchored_<mode>_dt_residual``; ``--validation-anchors`` compares the bases on
validation. ``--raf-width`` and ``--raf-conditional-blocks`` size the pure models;
``--evaluate-only CKPT...`` evaluates checkpoints trained outside the standard folder (chosen
beforehand on validation) on the held-out identities and the MakeHuman head next to the
baselines, training nothing.

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
import dataclasses
import json
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import (
    ANCHOR_CM,
    ANCHOR_MODES,
    STATIC_MM,
    RigAnyFaceTrainOptions,
    anchored_base_key,
    cached_transfer,
    class_errors,
    copy_poses,
    crop_below_chin,
    error_stats,
    evaluate_makehuman,
    face_placement,
    generate_rig,
    generate_rows,
    head_correspondence,
    head_inputs,
    ict_autorig_dataset,
    inner_outside,
    load_riganyface,
    normalise,
    penetration,
    penetration_free_set,
    sculpted_shape_errors,
    train_riganyface,
    training_set,
    transfer_bases,
    worst_poses,
)
from canrig_jax.canrig import parameter_count
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import export_gltf, load_gltf_rig
from canrig_jax.watchdog import run_watched

MODELS = {"raf": {}, "raf_no_global_encoder": {"global_size": 0}}
RAF_LOSSES = {
    "squared": {"loss": "squared", "static_weight": 0.0},
    "euclidean_static": {"loss": "euclidean", "static_weight": 1.0},
    "squared_static": {"loss": "squared", "static_weight": 1.0},
    "euclidean": {"loss": "euclidean", "static_weight": 0.0},
    "squared_static_balanced": {"loss": "squared", "static_weight": 1.0, "balance_poses": True},
    "squared_static_half_balanced": {
        "loss": "squared",
        "static_weight": 1.0,
        "balance_poses": 0.5,
    },
    "squared_static_balanced_0.3": {"loss": "squared", "static_weight": 1.0, "balance_poses": 0.3},
}
"""Losses of pure RAF (``--raf-loss``): the issue-7 recipe (the standard checkpoints), the
per-vertex Euclidean loss plus the static-vertex term (issue 19; experiments/results/
autorig_retrain, autorig_wide, autorig_long), and the other two combinations (the loss
ablation, experiments/results/autorig_loss), and squared + static with every pose weighed
against its own no-motion error (``RigAnyFaceTrainOptions.balance_poses``; autorig_balanced),
or halfway (balance_poses=0.5; autorig_half_balanced, and on 12,000 steps
autorig_half_balanced_long, the default model), or 0.3 of the way (autorig_balanced_03)."""
RESIDUAL = "raf_dt_residual"
RESIDUAL_ANCHORED = "raf_anchored_dt_residual"
"""The residual model trained on anchored deformation transfer (``--anchored-residual``)."""
ANCHORED_RESIDUALS = {
    RESIDUAL_ANCHORED: "vertex",
    **{f"raf_anchored_{mode}_dt_residual": mode for mode in ANCHOR_MODES if mode != "vertex"},
}
"""Residual models trained on anchored deformation transfer, by anchoring mode
(``transfer_poses(anchor=)``; ``--anchor``): per vertex (the standard), per part, per vertex on
the skin and per part elsewhere (issue 19, per-part anchoring)."""
ANCHORED = "_anchored"
"""Suffix of a row evaluated on anchored deformation transfer (``deformation_transfer_anchored``
and ``raf_dt_residual_anchored``: the plain-trained residual model on the anchored base)."""
RESIDUAL_OPTIONS = {"residual": True, "loss": "euclidean", "static_weight": 1.0}
BASELINES = ("no_motion", "copy_deltas", "deformation_transfer")
SPLITS = ("same_topology", "unseen_topology")
HELDOUT_SPLIT = "unseen_topology"


def _held_out_dataset(args, n_test: int, seed: int):
    """The standard run's held-out identities, for the evaluation-only paths: they come from
    their own random stream, so one training identity is enough to rebuild them (and no
    training head is used)."""
    return ict_autorig_dataset(
        args.data_dir,
        n_train=1,
        n_test=n_test,
        seed=seed,
        progress=not args.no_progress,
    )


def _train_one(args, name, data, poses, options):
    """Train (or resume) ``checkpoint_{name}.eqx`` in ``args.out``; (model, its record)."""
    path = args.out / f"checkpoint_{name}.eqx"
    result = train_riganyface(
        data, poses, options, checkpoint=path, progress=not args.no_progress, devices=args.devices
    )
    model, _, state = load_riganyface(path)
    print(f"{name}: {result.step} steps in {result.seconds / 60:.1f} min")
    return model, {
        "steps": result.step,
        "minutes": result.seconds / 60,
        "parameters": parameter_count(model),
        "final_train_error_mm": state["history"][-1]["error_mm"],
        "history": state["history"],
        "options": options.to_dict(),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="2 identities, 20 steps (tests)")
    parser.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="training-time budget per model (accumulated over resumed runs; default: none, "
        "the cosine schedule runs to --steps)",
    )
    parser.add_argument("--steps", type=int, default=2500, help="step budget per model")
    parser.add_argument("--train-identities", type=int, default=24)
    parser.add_argument("--test-identities", type=int, default=8)
    parser.add_argument("--learning-rate", type=float, default=1e-3)
    parser.add_argument(
        "--residual-steps",
        type=int,
        default=2000,
        help="steps of the DT + residual model (its cosine schedule ends there; no clock cut)",
    )
    parser.add_argument("--cache", type=Path, default=None, help="cache of transferred poses")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--devices",
        type=int,
        default=None,
        help="data-parallel training over N devices (default: all; see canrig_jax._sharding)",
    )
    parser.add_argument(
        "--timing-only",
        action="store_true",
        help="re-measure only rig_seconds of --out/results.json with its RAF checkpoint",
    )
    parser.add_argument(
        "--penetration-only",
        action="store_true",
        help="evaluate only (no training, no training data): measure penetration on the "
        "pose set where the ground truth has none, with the checkpoints in --out, into "
        "--out/results.json",
    )
    parser.add_argument(
        "--placement-only",
        action="store_true",
        help="evaluate only: RAF with the bounding-box placement against face_placement, on "
        "the held-out heads as they are and cut below the chin, into --out/results.json",
    )
    parser.add_argument(
        "--raf-loss",
        choices=tuple(RAF_LOSSES),
        default="squared",
        help="loss of raf and raf_no_global_encoder (default: %(default)s, the standard "
        "checkpoints' recipe)",
    )
    parser.add_argument(
        "--raf-width",
        type=int,
        default=RigAnyFaceTrainOptions.width,
        help="feature width of raf and raf_no_global_encoder (default: %(default)s, the "
        "standard checkpoints')",
    )
    parser.add_argument(
        "--raf-conditional-blocks",
        type=int,
        default=RigAnyFaceTrainOptions.n_conditional,
        help="pose-conditioned diffusion blocks of raf and raf_no_global_encoder (default: "
        "%(default)s)",
    )
    parser.add_argument(
        "--validation-only",
        type=Path,
        nargs="+",
        default=None,
        metavar="CHECKPOINT",
        help="evaluate only: these checkpoints, no motion and DT on validation identities "
        "(their own random stream: neither training nor held-out test identities) at the "
        "held-out resolution, into --out/validation.json; how models are chosen",
    )
    parser.add_argument("--validation-identities", type=int, default=4)
    parser.add_argument(
        "--evaluate-only",
        type=Path,
        nargs="+",
        default=None,
        metavar="CHECKPOINT",
        help="evaluate only: these checkpoints (chosen beforehand with --validation-only) next "
        "to no motion, copied deltas and DT on the held-out test identities and the MakeHuman "
        "head, into --out/results.json and table.md (a model trained outside the standard "
        "folder)",
    )
    parser.add_argument(
        "--validation-anchors",
        nargs="+",
        choices=ANCHOR_MODES,
        default=["vertex"],
        help="with --validation-only: anchored DT bases to compare (transfer_poses(anchor=): "
        "per vertex, per part, per vertex on the skin and per part elsewhere); default: "
        "%(default)s",
    )
    parser.add_argument(
        "--residual-gate",
        type=float,
        default=0.0,
        help="tau (unit-sphere units) of raf_dt_residual's gate on its correction, "
        "|b|^2 / (|b|^2 + tau^2) with b the DT displacement: what DT leaves still stays "
        "still (default: 0, no gate, the committed issue-19 model)",
    )
    parser.add_argument(
        "--residual-static-weight",
        type=float,
        default=RESIDUAL_OPTIONS["static_weight"],
        help="weight of raf_dt_residual's static-vertex term (default: %(default)s)",
    )
    parser.add_argument(
        "--anchored-residual",
        action="store_true",
        help=f"also train (or resume) and evaluate {RESIDUAL_ANCHORED}: the residual model "
        "with the same recipe on anchored deformation transfer (its training and evaluation "
        "base)",
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
    parser.add_argument(
        "--train-only",
        choices=(*MODELS, RESIDUAL, *ANCHORED_RESIDUALS),
        default=None,
        help="train (or resume) only this model's checkpoint in --out and stop: writes no "
        "results (a chunk of a long run, or the models in parallel processes); the standard "
        "command then resumes the finished checkpoints and evaluates",
    )
    args = parser.parse_args(argv)
    if args.validation_only:
        return validate(args, argv)
    if args.evaluate_only:
        return evaluate_checkpoints(args, argv)
    if args.placement_only:
        return refresh_placement(args, argv)
    if args.timing_only:
        return refresh_timing(args, argv)
    if args.penetration_only:
        return refresh_penetration(args, argv)
    progress = not args.no_progress
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    if args.train_only is None:
        record_command(args.out, command)

    start = time.perf_counter()
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=2 if args.quick else args.train_identities,
        n_test=1 if args.quick else args.test_identities,
        seed=args.seed,
        progress=progress,
    )
    poses = dataset.poses
    options = RigAnyFaceTrainOptions(
        steps=20 if args.quick else args.steps,
        warmup_steps=5 if args.quick else 200,
        max_minutes=None if args.quick else args.minutes,
        learning_rate=args.learning_rate,
        seed=args.seed,
        checkpoint_every=10 if args.quick else 200,
    )
    models, trained = {}, {}
    if args.train_only not in (RESIDUAL, *ANCHORED_RESIDUALS):
        data = training_set(dataset.train, poses, k=options.k, progress=progress)
        print(
            f"{len(dataset.train)} training heads ({data.vertices.shape[1]} padded vertices), "
            f"{poses.n_poses} poses, data in {time.perf_counter() - start:.0f} s"
        )

    # -- training (resumes from the checkpoints) ----------------------------------------------
    for name, overrides in MODELS.items():
        if args.train_only not in (None, name):
            continue
        model_options = dataclasses.replace(
            options,
            **RAF_LOSSES[args.raf_loss],
            width=args.raf_width,
            n_conditional=args.raf_conditional_blocks,
            **overrides,
        )
        models[name], trained[name] = _train_one(args, name, data, poses, model_options)
    if args.train_only in MODELS:
        return None

    # -- DT + learned residual: the training heads' transferred poses are its base --------
    residual_options = dataclasses.replace(
        options,
        **{**RESIDUAL_OPTIONS, "static_weight": args.residual_static_weight},
        residual_gate=args.residual_gate,
        steps=20 if args.quick else args.residual_steps,
        warmup_steps=5 if args.quick else min(200, args.residual_steps // 10),
        max_minutes=None,
    )
    anchors = ("vertex",) if args.anchor == "vertex" else ("vertex", args.anchor)
    residuals = {RESIDUAL: None}  # name -> anchoring mode of its base (None: plain DT)
    for name, mode in ANCHORED_RESIDUALS.items():
        if (args.anchored_residual and mode in anchors) or args.train_only == name:
            residuals[name] = mode
    for name, mode in residuals.items():
        if args.train_only not in (None, name):
            continue
        base = [
            cached_transfer(
                dataset,
                head,
                args.cache,
                args.seed,
                None if mode is None else ANCHOR_CM,
                anchor=mode or "vertex",
            )
            for head in dataset.train
        ]
        data = training_set(dataset.train, poses, k=options.k, progress=progress, base=base)
        models[name], trained[name] = _train_one(args, name, data, poses, residual_options)
        key = "" if mode is None else "_" + anchored_base_key(mode)
        trained[name]["base"] = "deformation_transfer" + key
        del data, base
    if args.train_only is not None:
        return None

    # -- evaluation on held-out heads ------------------------------------------------------------
    part_names = dataset.head.part_names
    rows = evaluation_rows(models)
    anchored_dt = {
        "deformation_transfer_" + anchored_base_key(m): anchored_base_key(m) for m in anchors
    }
    methods = (*BASELINES, *anchored_dt, *rows)
    test: dict = {name: {} for name in methods if name != "no_motion"}
    pen: dict = {name: [] for name in (*rows, "ground_truth")}
    examples, heldout_predictions, heldout_truth = {}, {name: [] for name in methods}, []
    for split in SPLITS:
        truth_all, unit_scale = [], []
        predicted_all = {name: [] for name in test}
        for head in dataset.test[split]:
            unit, operators, _, scale = head_inputs(head.vertices, head.faces, k=options.k)
            truth_all.append(head.displacements)
            unit_scale.append(scale)
            correspondence = head_correspondence(dataset, head.vertices, head.faces, head.landmarks)
            bases = transfer_bases(dataset, head, correspondence, anchors=anchors)
            predicted_all["deformation_transfer"].append(bases["plain"])
            for name, key in anchored_dt.items():
                predicted_all[name].append(bases[key])
            predicted_all["copy_deltas"].append(copy_poses(dataset, head, correspondence))
            generated_rigs = generate_rows(models, rows, poses, head, bases, operators=operators)
            for name, generated in generated_rigs.items():
                predicted_all[name].append(generated.displacements)
                pen[name].append(penetration(head, generated.displacements, part_names))
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
        if split == HELDOUT_SPLIT:
            heldout_truth = truth_all
            heldout_predictions = {"no_motion": [np.zeros_like(t) for t in truth_all]}
            heldout_predictions.update(predicted_all)
    heldout = {
        name: class_errors(p, heldout_truth, poses) for name, p in heldout_predictions.items()
    }
    worst = {
        name: worst_poses(p, heldout_truth, poses, 5) for name, p in heldout_predictions.items()
    }

    # -- MakeHuman hm08 against its person-made targets (evaluation only) -----------------
    makehuman, makehuman_info, makehuman_example = evaluate_makehuman(
        dataset, models, evaluation_rows(models), args.data_dir, anchors
    )

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
        "heldout": heldout,
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
            "heads": len(heldout_truth),
            "static_mm": STATIC_MM,
            "static": "a (pose, vertex) pair whose ground-truth displacement is < static_mm",
        },
        "worst_poses": worst,
        "makehuman": makehuman,
        "makehuman_protocol": makehuman_info,
        "makehuman_shapes": makehuman_shapes(makehuman_example),
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
    plot_examples(args.out, poses.labels, examples, makehuman_example)


def evaluation_rows(models: dict) -> dict:
    """Row name -> (model name, base: None, "plain" or an anchored deformation transfer's key):
    the pure models, the residual model on plain DT (as trained) and on anchored DT
    (``raf_dt_residual_anchored``), and the residual models trained on anchored DT (each on its
    own base)."""
    rows = {}
    for name, model in models.items():
        if not model.residual:
            rows[name] = (name, None)
        elif name in ANCHORED_RESIDUALS:
            rows[name] = (name, anchored_base_key(ANCHORED_RESIDUALS[name]))
        else:
            rows[name] = (name, "plain")
            rows[name + ANCHORED] = (name, "anchored")
    return rows


UPPER_FACE = ("brow", "eye", "cheekSquint")
"""ARKit shapes of the upper face (name prefixes), for the per-region MakeHuman summary."""


def makehuman_shapes(makehuman_example: tuple) -> dict:
    """Per shape on the MakeHuman head (``sculpted_shape_errors``) of every method in
    ``evaluate_makehuman``'s example: {"labels", "target_peak_mm", "upper_face": (S,) bool,
    "methods": name -> {"skin_mae_mm", "amplitude_ratio", "peak_mm"}}, lists."""
    mh, truth, predictions, labels = makehuman_example
    methods, target_peak = {}, None
    for name, predicted in predictions.items():
        errors = sculpted_shape_errors(predicted, truth, mh.skin)
        target_peak = errors.pop("target_peak_mm")
        errors["peak_ratio"] = errors["peak_mm"] / target_peak
        methods[name] = {k: v.tolist() for k, v in errors.items()}
    return {
        "labels": [str(n) for n in labels],
        "target_peak_mm": target_peak.tolist(),
        "upper_face": [str(n).startswith(UPPER_FACE) for n in labels],
        "methods": methods,
    }


def heldout_shapes(heads, predicted: dict, poses) -> dict:
    """Per single expression on the held-out ICT heads (``sculpted_shape_errors`` against the
    ground truth on each head's skin, Face and Head and Neck, then the mean over heads):
    {"labels", "upper_face", "methods": name -> {"skin_mae_mm", "amplitude_ratio",
    "peak_ratio"}}, lists. An aggregate MAE can hide a region that never moves: most vertices
    of an eye or brow shape are static."""
    n = poses.n_basis
    methods = {}
    for name, per_head in predicted.items():
        if name == "no_motion":
            continue
        records = []
        for head, p in zip(heads, per_head, strict=True):
            e = sculpted_shape_errors(p[:n], head.displacements[:n], head.parts <= 1)
            records.append({**e, "peak_ratio": e["peak_mm"] / e["target_peak_mm"]})
        methods[name] = {
            k: np.mean([r[k] for r in records], axis=0).tolist()
            for k in ("skin_mae_mm", "amplitude_ratio", "peak_ratio")
        }
    labels = [str(name) for name in poses.basis_names]
    return {
        "labels": labels,
        "upper_face": [name.startswith(UPPER_FACE) for name in labels],
        "methods": methods,
    }


def shape_region_rows(shapes: dict, figure: str) -> list[str]:
    """Table rows: each method's median per-shape amplitude ratio, peak ratio and skin MAE on
    the upper face (brow, eye, cheekSquint shapes) and on the rest (``makehuman_shapes``,
    ``heldout_shapes``)."""
    upper = np.asarray(shapes["upper_face"])
    rows = [
        f"Per shape, by region (median over shapes; upper face: {', '.join(UPPER_FACE)}*, "
        f"{upper.sum()} shapes; lower face: the other {(~upper).sum()}; {figure}):",
        "",
        "| method | amplitude ratio upper / lower | peak ratio upper / lower | "
        "skin MAE upper / lower (mm) |",
        "|---|---|---|---|",
    ]
    for name, e in shapes["methods"].items():
        ratio, mae = np.asarray(e["amplitude_ratio"]), np.asarray(e["skin_mae_mm"])
        peak = np.asarray(e["peak_ratio"])
        cells = [
            f"{np.median(x[upper]):{f}} / {np.median(x[~upper]):{f}}"
            for x, f in ((ratio, ".2f"), (peak, ".2f"), (mae, ".3f"))
        ]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return [*rows, "", "Amplitude: summed motion on the skin; peak: its largest vertex motion.", ""]


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
        "warm_orientation": float(np.median([w.get("orientation", 0.0) for w in warm])),
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
    model, poses, _ = load_riganyface(checkpoint)
    results["rig_seconds"] = rig_timing(model, poses, load_ict(args.data_dir, parts=None))
    results["timing_provenance"] = provenance(experiment_command(__file__, argv))
    write_results(args.out, results)
    print(f"rewrote rig_seconds of {path} and table.md")
    return results


VALIDATION_SEED_OFFSET = 1000
"""Validation identities are the held-out stream of seed + this: no training identity (stream
[seed, 0]) and no held-out test identity (stream [seed, 1]) is among them."""


def _load_checkpoints(paths, flag: str) -> dict:
    """Row name ("<folder>/<file stem>") -> (model, header) of each checkpoint in ``paths``."""
    models = {}
    for path in paths:
        if not path.exists():
            raise ValueError(f"{flag}: no checkpoint {path}")
        model, _, header = load_riganyface(path)
        models[f"{path.parent.name}/{path.stem}"] = model, header
    return models


def _checkpoint_predictions(dataset, models: dict, anchors, copy: bool = False, rows=None):
    """Every unseen-topology held-out head of ``dataset``: (row -> predictions per head,
    ground truth per head) for no motion, (copied ICT deltas,) DT plain and anchored per each
    mode of ``anchors``, and each of ``rows`` (row -> (model name, base key or None); default:
    each checkpoint, a residual one on every base)."""
    anchored = [anchored_base_key(mode) for mode in anchors]
    if rows is None:
        rows = {}
        for name, model in models.items():
            for base in ("plain", *anchored) if model.residual else (None,):
                rows[name if base in (None, "plain") else f"{name}+{base}_base"] = (name, base)
    dt = {"deformation_transfer": "plain"}
    dt.update({f"deformation_transfer_{key}": key for key in anchored})
    baselines = ("no_motion", "copy_deltas") if copy else ("no_motion",)
    predicted = {name: [] for name in (*baselines, *dt, *rows)}
    truth = []
    for head in dataset.test[HELDOUT_SPLIT]:
        correspondence = head_correspondence(dataset, head.vertices, head.faces, head.landmarks)
        bases = transfer_bases(dataset, head, correspondence, anchors=tuple(anchors))
        truth.append(head.displacements)
        predicted["no_motion"].append(np.zeros_like(head.displacements))
        if copy:
            predicted["copy_deltas"].append(copy_poses(dataset, head, correspondence))
        for name, key in dt.items():
            predicted[name].append(bases[key])
        for name, generated in generate_rows(models, rows, dataset.poses, head, bases).items():
            predicted[name].append(generated.displacements)
        print(f"predicted {head.name}")
    return predicted, truth


def validate(args, argv=None) -> dict:
    """Errors by pose and vertex class (``class_errors``) of ``args.validation_only``'s
    checkpoints, no motion and DT on validation identities at the held-out resolution, and
    their per-shape record (``heldout_shapes``: does the upper face move?); written to
    ``args.out``/validation.json. Evaluation only: nothing is trained."""
    models = {
        name: model
        for name, (model, _) in _load_checkpoints(args.validation_only, "--validation-only").items()
    }
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=1,
        n_test=args.validation_identities,
        seed=args.seed + VALIDATION_SEED_OFFSET,
        progress=not args.no_progress,
    )
    predicted, truth = _checkpoint_predictions(dataset, models, args.validation_anchors)
    results = {
        "validation": {
            name: class_errors(p, truth, dataset.poses) for name, p in predicted.items()
        },
        "validation_shapes": heldout_shapes(dataset.test[HELDOUT_SPLIT], predicted, dataset.poses),
        "protocol": {
            "identities": f"held-out stream of seed {args.seed + VALIDATION_SEED_OFFSET} "
            f"(not training, not test), {len(truth)} heads",
            "split": HELDOUT_SPLIT,
            "static_mm": STATIC_MM,
            "bases": "a residual checkpoint's row uses plain deformation transfer as its base; "
            f"'+anchored_base' rows anchored DT (static_below = {ANCHOR_CM} cm)",
            "anchors": {
                anchored_base_key(m): f"transfer_poses(static_below={ANCHOR_CM}, anchor={m!r})"
                for m in args.validation_anchors
            },
        },
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "validation.json", results)
    for name, classes in results["validation"].items():
        print(
            name,
            " ".join(
                f"{c}: mae {v['mae_mm']:.4f} static {v['static_mae_mm']:.4f} "
                f"moving {v['moving_mae_mm']:.4f}"
                for c, v in classes.items()
            ),
        )
    upper = np.asarray(results["validation_shapes"]["upper_face"])
    for name, e in results["validation_shapes"]["methods"].items():
        peak = np.asarray(e["peak_ratio"])
        print(
            f"{name} median peak ratio: upper face {np.median(peak[upper]):.2f}, "
            f"lower face {np.median(peak[~upper]):.2f}"
        )
    return results


def evaluate_checkpoints(args, argv=None) -> dict:
    """``args.evaluate_only``'s checkpoints (chosen beforehand, on validation identities)
    against no motion, copied ICT deltas and DT (plain and anchored) on the standard held-out
    test identities (unseen topology) and on the MakeHuman head, with penetration where the
    ground truth has none (``clean_penetration``): results.json (``heldout``, ``worst_poses``,
    ``heldout_shapes``, ``makehuman``, ``makehuman_shapes``, ``penetration_clean``,
    ``training``), table.md, training_loss.png, poses_unseen_topology.png, heldout_shapes.png,
    makehuman.png and makehuman_shapes.png in ``args.out``. Nothing is trained."""
    loaded = _load_checkpoints(args.evaluate_only, "--evaluate-only")
    models = {name: model for name, (model, _) in loaded.items()}
    training = {}
    for name, (model, state) in loaded.items():
        training[name] = {
            "steps": state["step"],
            "minutes": state["seconds"] / 60,
            "parameters": parameter_count(model),
            "final_train_error_mm": state["history"][-1]["error_mm"],
            "history": state["history"],
            "options": state["options"],
        }
    start = time.perf_counter()
    dataset = _held_out_dataset(args, args.test_identities, args.seed)
    poses = dataset.poses
    predicted, truth = _checkpoint_predictions(dataset, models, ("vertex",), copy=True)
    makehuman, makehuman_info, makehuman_example = evaluate_makehuman(
        dataset, models, evaluation_rows(models), args.data_dir, face_placed=True
    )
    heads, part_names = dataset.test[HELDOUT_SPLIT], dataset.head.part_names
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
        "heldout_shapes": heldout_shapes(dataset.test[HELDOUT_SPLIT], predicted, poses),
        "makehuman": makehuman,
        "makehuman_protocol": makehuman_info,
        "makehuman_shapes": makehuman_shapes(makehuman_example),
        **clean_penetration(heads, predicted, poses, part_names),
        "parameters": {name: t["parameters"] for name, t in training.items()},
        "training": {
            name: {k: v for k, v in t.items() if k != "history"} for name, t in training.items()
        },
        "total_minutes": (time.perf_counter() - start) / 60,
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    training_header = ["## Training", "", "| quantity | value |", "|---|---|"]
    penetration_header = ["## Penetration (Table 2 analog)"]
    text = heldout_table(results) + penetration_header + penetration_clean_rows(results)
    text = "\n".join([*text, "", *training_header, *training_rows(results)]) + "\n"
    save_text(args.out / "table.md", text)
    print(text)
    plot_history(training, args.out / "training_loss.png")
    first = {name: p[0] for name, p in predicted.items() if name != "no_motion"}
    examples = {HELDOUT_SPLIT: (heads[0], first)}
    plot_examples(args.out, poses.labels, examples, makehuman_example)
    plot_shape_ratios(
        results["heldout_shapes"],
        f"Held-out ICT identities ({len(heads)} heads, {HELDOUT_SPLIT})",
        args.out / "heldout_shapes.png",
    )
    return results


def clean_penetration(heads, predicted: dict, poses, part_names) -> dict:
    """Penetration where the ground truth has none (``penetration_free_set``: per head, the
    inner vertices inside the skin at rest and the poses whose ground truth pushes none of them
    out) of each row of ``predicted`` (row -> (P, V, 3) per head) and of the ground truth, and
    the plain penetration re-measured: results.json's ``penetration_clean``,
    ``penetration_clean_protocol`` and ``penetration_remeasured``."""
    predicted = {**predicted, "ground_truth": [head.displacements for head in heads]}
    clean = {name: [] for name in predicted}
    plain = {name: [] for name in predicted}
    chosen, kept_vertices = [], []
    for i, head in enumerate(heads):
        pose_index, vertices = penetration_free_set(head, part_names)
        chosen.append(pose_index)
        kept_vertices.append(int(vertices.sum()))
        for name, displacements in predicted.items():
            outside = inner_outside(head, displacements[i], part_names)
            plain[name].append(float(outside.mean()))
            clean[name].append(outside[pose_index][:, vertices])
        print(f"{head.name}: {pose_index.size} of {poses.n_poses} poses without penetration")
    counts = np.bincount(np.concatenate(chosen), minlength=poses.n_poses)
    return {
        "penetration_clean": {
            name: {
                "fraction": float(np.mean(np.concatenate([o.ravel() for o in outs]))),
                "poses_with_any": float(np.mean(np.concatenate([o.any(axis=1) for o in outs]))),
            }
            for name, outs in clean.items()
        },
        "penetration_clean_protocol": {
            "split": HELDOUT_SPLIT,
            "heads": len(chosen),
            "selection": "per head: inner vertices (teeth, gums, eyeballs) inside the skin at "
            "rest; poses whose ground truth pushes none of them outside (threshold 0)",
            "fraction": "outside fraction over the selected (pose, vertex) pairs of all heads",
            "poses_with_any": "fraction of selected (head, pose) pairs with any vertex outside",
            "poses_per_head": [int(c.size) for c in chosen],
            "inner_vertices_per_head": kept_vertices,
            "poses_selected_on_every_head": [
                poses.labels[i] for i in np.flatnonzero(counts == len(chosen))
            ],
        },
        "penetration_remeasured": {n: float(np.mean(v)) for n, v in plain.items()},
    }


def refresh_penetration(args, argv=None) -> dict:
    """Penetration of every held-out method on the pose set where the ground truth has none
    (``penetration_free_set``: per head, the inner vertices inside the skin at rest and the
    poses whose ground truth pushes none of them out), with the checkpoints in ``args.out``;
    the rest of results.json is kept. Evaluation only: nothing is trained."""
    path = args.out / "results.json"
    names = [*MODELS, RESIDUAL]
    missing = [n for n in names if not (args.out / f"checkpoint_{n}.eqx").exists()]
    if not path.exists() or missing:
        raise ValueError(
            f"--penetration-only: needs results.json and the checkpoints of {names} in "
            f"{args.out}; run without --penetration-only first"
        )
    anchors = ["vertex"]
    for name, mode in ANCHORED_RESIDUALS.items():
        if (args.out / f"checkpoint_{name}.eqx").exists():
            names.append(name)
            anchors += [] if mode in anchors else [mode]
    results = json.loads(path.read_text())
    config = results["config"]
    models = {n: load_riganyface(args.out / f"checkpoint_{n}.eqx")[0] for n in names}
    dataset = _held_out_dataset(args, config["test_identities"], config["options"]["seed"])
    predicted, _ = _checkpoint_predictions(dataset, models, anchors, rows=evaluation_rows(models))
    heads, part_names = dataset.test[HELDOUT_SPLIT], dataset.head.part_names
    results.update(clean_penetration(heads, predicted, dataset.poses, part_names))
    results["penetration_provenance"] = provenance(experiment_command(__file__, argv))
    write_results(args.out, results)
    print(f"rewrote the penetration of {path} and table.md")
    return results


def refresh_placement(args, argv=None) -> dict:
    """RAF (the committed checkpoint) placed by the bounding box (as trained) and by
    ``face_placement``, on the held-out heads whole and cut 1 cm below the chin; the rest of
    results.json is kept. Evaluation only: nothing is trained."""
    path, checkpoint = args.out / "results.json", args.out / "checkpoint_raf.eqx"
    if not path.exists() or not checkpoint.exists():
        raise ValueError(
            f"--placement-only: needs results.json and checkpoint_raf.eqx in {args.out}; "
            "run without --placement-only first"
        )
    results = json.loads(path.read_text())
    config = results["config"]
    model, poses, _ = load_riganyface(checkpoint)
    dataset = _held_out_dataset(args, config["test_identities"], config["options"]["seed"])
    errors: dict = {}
    scales: dict = {"whole": [], "cut": []}
    fit_seconds = []
    for head in dataset.test[HELDOUT_SPLIT]:
        cut, kept = crop_below_chin(head)
        truth = head.displacements[:, kept]
        for crop, mesh in (("whole", head), ("cut", cut)):
            start = time.perf_counter()
            placement = face_placement(dataset, mesh.vertices, mesh.faces)
            fit_seconds.append(time.perf_counter() - start)
            _, _, box_scale = normalise(mesh.vertices)
            scales[crop].append({"bounding_box_cm": box_scale, "face_cm": placement[1]})
            for how, where in (("bounding_box", None), ("face", placement)):
                predicted = generate_rig(
                    model, poses, mesh.vertices, mesh.faces, placement=where
                ).displacements
                if crop == "whole":
                    predicted = predicted[:, kept]  # compared on the vertices both share
                errors.setdefault(f"{crop}/{how}", []).append((predicted, truth))
        print(f"{head.name}: {int(kept.sum())} of {head.n_vertices} vertices above the cut")
    results["placement"] = {
        key: error_stats(
            np.concatenate([p for p, _ in pairs], 1), np.concatenate([t for _, t in pairs], 1)
        )
        for key, pairs in errors.items()
    }
    results["placement_protocol"] = {
        "split": HELDOUT_SPLIT,
        "heads": len(dataset.test[HELDOUT_SPLIT]),
        "model": "raf",
        "cut": "triangles reaching below the chin landmark minus 1 cm removed",
        "compared_on": "the vertices above the cut (both crops)",
        "face": "face_placement: trimmed-ICP similarity of the ICT face part, the generic ICT "
        "head's bounding-box centre and radius carried through it",
        "scale_cm": {
            crop: {k: float(np.mean([s[k] for s in v])) for k in v[0]} for crop, v in scales.items()
        },
        "seconds_face_fit_median": float(np.median(fit_seconds)),
    }
    results["placement_provenance"] = provenance(experiment_command(__file__, argv))
    write_results(args.out, results)
    print(f"rewrote the placement of {path} and table.md")
    return results


def write_results(out: Path, results: dict) -> None:
    """results.json and table.md in ``out`` (atomic), and the table on stdout."""
    save_json(out / "results.json", results)
    text = table(results)
    save_text(out / "table.md", text)
    print(text)


def table(r: dict) -> str:
    rows = heldout_table(r) if "heldout" in r else []
    rows += [
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
    rows += penetration_clean_rows(r)
    if "placement" in r:
        p, e = r["placement_protocol"], r["placement"]
        sc = p["scale_cm"]
        rows += [
            "",
            f"## Placement: bounding box (as trained) or face ({p['model']}, {p['heads']} heads, "
            f"{p['split']})",
            "",
            f"Cut: {p['cut']}; compared on {p['compared_on']}. Face: {p['face']}. Mean scale "
            f"(cm): whole head box {sc['whole']['bounding_box_cm']:.2f} / face "
            f"{sc['whole']['face_cm']:.2f}; cut head box {sc['cut']['bounding_box_cm']:.2f} / "
            f"face {sc['cut']['face_cm']:.2f}. Face fit {p['seconds_face_fit_median']:.1f} s "
            "per head (median).",
            "",
            "| head | placement | MAE (mm) | q95 (mm) |",
            "|---|---|---|---|",
        ]
        rows += [
            f"| {key.split('/')[0]} | {key.split('/')[1]} | {v['mae_mm']:.3f} | {v['q95_mm']:.3f} |"
            for key, v in e.items()
        ]
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
    if "warm_orientation" in t:
        rows.append(f"| of which the orientation check (s) | {t['warm_orientation']:.3f} |")
    rows += []
    rows += training_rows(r)
    g = r["gltf"]
    rows += [
        f"| glTF export: morph targets / max abs difference after reload (cm) | "
        f"{g['morph_targets']} / {g['max_abs_difference_cm']:.2e} |"
    ]
    return "\n".join(rows) + "\n"


def penetration_clean_rows(r: dict) -> list[str]:
    """Table of ``penetration_clean`` (none when results.json has no such key)."""
    if "penetration_clean" not in r:
        return []
    p = r["penetration_clean_protocol"]
    return [
        "",
        f"Where the ground truth has none ({p['heads']} heads, {p['split']}; "
        f"{p['selection']}; {min(p['poses_per_head'])}-{max(p['poses_per_head'])} poses "
        "per head): outside fraction of those (pose, vertex) pairs, and the fraction of "
        "those poses with any vertex outside. Plain penetration re-measured alongside.",
        "",
        "| method | outside fraction | poses with any | plain (re-measured) |",
        "|---|---|---|---|",
        *(
            f"| {name} | {c['fraction']:.5f} | {c['poses_with_any']:.3f} | "
            f"{r['penetration_remeasured'][name]:.4f} |"
            for name, c in r["penetration_clean"].items()
        ),
    ]


def training_rows(r: dict) -> list[str]:
    """Table rows: parameters, steps, minutes and final training-batch error of each model."""
    return [f"| parameters {name} | {n:,} |" for name, n in r["parameters"].items()] + [
        f"| training {name}: steps / minutes / final batch error (mm) | {t['steps']} / "
        f"{t['minutes']:.1f} / {t['final_train_error_mm']:.3f} |"
        for name, t in r["training"].items()
    ]


def heldout_table(r: dict) -> list[str]:
    p = r["heldout_protocol"]
    rows = [
        f"## Held-out ICT identities ({p['heads']} heads, {p['split']}): vertex error in mm",
        "",
        f"Static: a (pose, vertex) pair whose ground-truth displacement is < {p['static_mm']} "
        "mm; moving: the others.",
        "",
        "| method | single MAE | single q95 | single static | single moving | "
        "combinations MAE | comb. q95 | comb. static | comb. moving |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, subsets in r["heldout"].items():
        cells = [
            f"{subsets[s][k]:.3f}"
            for s in ("single", "combinations")
            for k in ("mae_mm", "q95_mm", "static_mae_mm", "moving_mae_mm")
        ]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    rows += ["", "Worst five poses (MAE, mm):", "", "| method | worst poses |", "|---|---|"]
    for name, worst in r["worst_poses"].items():
        rows.append(
            f"| {name} | " + ", ".join(f"{w['pose']} {w['mae_mm']:.2f}" for w in worst) + " |"
        )
    if "heldout_shapes" in r:
        rows += ["", *shape_region_rows(r["heldout_shapes"], "heldout_shapes.png")]
    m = r["makehuman_protocol"]
    rows += [
        "",
        f"## MakeHuman hm08 ({m['vertices']} vertices) against its person-made ARKit targets "
        f"({m['shared_shapes']} shapes shared with ICT), mm",
        "",
        f"Active: (shape, vertex) pairs the sculptor moved by more than {m['active_mm']} mm. "
        f"Alignment: {m['alignment']} (scale {m['fit_scale']:.3f}, trimmed RMS "
        f"{m['fit_trimmed_rms_cm'] * 10:.2f} mm). Evaluation only: nothing trained or tuned on "
        "it.",
        "",
        "| method | MAE skin | q95 skin | MAE active | amplitude ratio (median) |",
        "|---|---|---|---|---|",
    ]
    for name, e in r["makehuman"].items():
        rows.append(
            f"| {name} | {e['skin_mae_mm']:.3f} | {e['skin_q95_mm']:.2f} | "
            f"{e['active_mae_mm']:.2f} | {e['amplitude_ratio_median']:.2f} |"
        )
    matched = ", ".join(f"{k} -> {v}" for k, v in m["matched_parts"].items())
    rows += ["", f"Part matching (MakeHuman component -> ICT part): {matched}.", ""]
    if "makehuman_shapes" in r:
        rows += shape_region_rows(r["makehuman_shapes"], "makehuman_shapes.png")
    return rows


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


def plot_examples(out: Path, labels, examples: dict, makehuman_example: tuple) -> None:
    """out/poses_<split>.png of each held-out example head (split -> (head, row ->
    predictions)) on its skin, out/makehuman.png and out/makehuman_shapes.png
    (``evaluate_makehuman``'s example)."""
    for split, (head, predictions) in examples.items():
        skin = head.parts <= 1
        plot_poses(
            head.vertices,
            head.faces[skin[head.faces].all(axis=1)],
            head.displacements,
            predictions,
            labels,
            out / f"poses_{split}.png",
        )
    mh, truth, predictions, mh_labels = makehuman_example
    plot_poses(
        mh.neutral,
        mh.faces[mh.skin[mh.faces].all(axis=1)],
        truth,
        predictions,
        mh_labels,
        out / "makehuman.png",
    )
    plot_shape_ratios(
        makehuman_shapes(makehuman_example),
        "MakeHuman hm08 against its sculpted targets",
        out / "makehuman_shapes.png",
    )


def _wrapped(name: str) -> str:
    """A method's name broken at its folder and placement so that figure columns do not overlap."""
    return name.replace("/", "/\n").replace(" + ", "\n+ ")


def plot_shape_ratios(shapes: dict, title: str, path: Path) -> None:
    """Each method's per-shape amplitude ratio (summed motion on the skin) and peak ratio
    (largest vertex motion), generated over true (log scale; 1: the true amount), shapes in
    alphabetical order, the upper face shaded (``makehuman_shapes``, ``heldout_shapes``)."""
    labels = shapes["labels"]
    order = np.argsort(labels)
    upper = np.asarray(shapes["upper_face"])[order]
    fig, axes = plt.subplots(2, 1, figsize=(13, 7.5), sharex=True)
    for ax, key, what in zip(
        axes, ("amplitude_ratio", "peak_ratio"), ("summed motion", "peak motion"), strict=True
    ):
        for x in np.flatnonzero(upper):
            ax.axvspan(x - 0.5, x + 0.5, color="0.92", lw=0)
        for name, e in shapes["methods"].items():
            ratio = np.maximum(np.asarray(e[key])[order], 1e-2)
            ax.plot(np.arange(len(labels)), ratio, "o-", ms=3, lw=0.7, label=name)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_yscale("log")
        ax.set_ylabel(f"{what} on the skin,\ngenerated / true")
    axes[1].set_xticks(np.arange(len(labels)), [labels[i] for i in order], rotation=90, fontsize=7)
    axes[1].set_xlim(-0.5, len(labels) - 0.5)
    axes[0].set_title(f"{title}, per shape (grey: upper face)")
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the data
    save_figure(fig, path)


def plot_poses(vertices, faces, truth, predictions: dict, labels, path: Path, n_poses=4):
    """Ground truth and each method's prediction for the poses that move most, coloured by
    error (0-5 mm; ground truth coloured by displacement), on ``faces`` (e.g. the skin)."""
    size = np.linalg.norm(truth, axis=-1).mean(axis=1)
    chosen = np.argsort(-size)[:n_poses]
    columns = ["ground_truth", *predictions]
    fig, axes = plt.subplots(n_poses, len(columns), figsize=(3 * len(columns), 3.2 * n_poses))
    for row, p in enumerate(chosen):
        for col, name in enumerate(columns):
            displaced = truth[p] if name == "ground_truth" else predictions[name][p]
            if name == "ground_truth":
                values = np.linalg.norm(truth[p], axis=-1) * CM_TO_MM
            else:
                values = np.linalg.norm(displaced - truth[p], axis=-1) * CM_TO_MM
            mappable = plot_vertex_scalar(
                axes[row, col],
                vertices + displaced,
                faces,
                values,
                vmax=5.0,
                title=f"{_wrapped(name)}\n{labels[p]}" if row == 0 or col == 0 else None,
            )
    fig.colorbar(
        mappable, ax=axes, shrink=0.5, label="mm (ground truth: displacement; others: error)"
    )
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
