"""CANRig workflows on real data: pose A to B (direct and fitted), iterative layers, clip
editing and dialogue replacement on the ict-quartic rig (issue 17).

    python experiments/canrig_workflows.py \
        --checkpoint experiments/results/canrig_workflows/model/checkpoint.eqx \
        --out experiments/results/canrig_workflows

Held-out poses: the Live Link capture's second half (frames 90-179) and 100 random sparse
poses (``canrig.held_out_poses``, as ``canrig_eval.py``). Table 4 as the paper runs it: random
(A, B) pairs of held-out poses, A != B, handles at random vertices (a new set per pair),
20/75/200 handles x 1/2/4 cm, falloff 3/cm, the error of the result against B averaged over
all 9,409 face vertices. Geodesic farthest-point handles from vertex 0 (``canrig_eval.py``'s
placement) are reported beside it as a second protocol. Writes results.json, table.md and
figures (a_to_b_error.png, layers.png, clip_edit.png, dialogue.png).

``--rig local-fit`` runs every workflow on ``canrig.LocalFitRig``, a rig with no network
(beyond the paper), instead of the checkpoint:

    python experiments/canrig_workflows.py --rig local-fit \
        --out experiments/results/canrig_workflows_local_fit
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.canrig import (
    EVAL_FALLOFF_PER_CM,
    RADII_CM,
    FitOptions,
    NeuralRig,
    clip_edit,
    dialogue_replacement,
    evaluate_poses,
    expression_region,
    farthest_point_vertices,
    global_blendshape_dialogue,
    held_out_poses,
    influence_mask,
    influence_reach,
    interior_vertices,
    iterative_layers,
    load_model,
    local_fit_rig,
    max_acceleration,
    patch_layout,
    pbs_basis,
    pose_a_to_b,
    split_capture,
)
from canrig_jax.data import load_livelinkface
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import ict_quartic_rig, random_sparse_poses
from canrig_jax.watchdog import run_watched

FALLOFF_PER_CM = EVAL_FALLOFF_PER_CM
HANDLE_COUNTS = (20, 75, 200)
LAYER_SCHEDULE = ((20, 4.0), (75, 2.0), (200, 1.0))
DISTANCE_LIMIT_CM = 5.0  # > the reach of a 4 cm mask at falloff 3/cm (4.77 cm): exact
CLIP_HANDLES, CLIP_HALF_WINDOW, CLIP_RADIUS_CM = 12, 10, 3.0
DIALOGUE_HANDLES, DIALOGUE_RADIUS_CM = 60, 1.5
MOUTH_THRESHOLD_CM = 0.3  # the mouth mask: what jaw*/mouth* move > 3 mm, eye*/brow* do not


def _error_mm(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1) * CM_TO_MM


def _timed(fn, repeats=5):
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


def _pairs(n_poses, n_pairs, rng):
    a = rng.integers(0, n_poses, n_pairs)
    b = (a + rng.integers(1, n_poses, n_pairs)) % n_poses
    return np.stack([a, b], axis=1)


def _random_protocol(n_shapes, n_vertices, args):
    """Table 4's (A, B) pairs, per handle count one random handle set per pair, and the
    handle generator in the state the rest of the experiment continues from."""
    pairs = _pairs(n_shapes, args.pairs, np.random.default_rng(args.seed))
    handle_rng = np.random.default_rng([args.seed, 1])
    random_sets = {
        n: [handle_rng.choice(n_vertices, n, replace=False) for _ in range(args.pairs)]
        for n in HANDLE_COUNTS
    }
    return pairs, random_sets, handle_rng


def unreached_floor(rig, shapes, pairs, random_sets, progress=print):
    """{handles: {radius name: {floor_mm, unreached_percent}}}: a lower bound of any A-to-B
    result under Table 4's random-vertex protocol. A vertex beyond every handle's reach
    (``influence_reach``: its clamped masks are exactly 0) keeps A's position whatever the
    network or the fit, so its error |A - B| is in every result; the floor is that error
    averaged over all vertices (0 on reached ones)."""
    table = {}
    for n in HANDLE_COUNTS:
        floors = {name: [] for name in RADII_CM}
        unreached = {name: [] for name in RADII_CM}
        for p, (a, b) in enumerate(pairs):
            nearest = np.asarray(
                rig.handles(random_sets[n][p], limit=DISTANCE_LIMIT_CM).distance
            ).min(axis=1)
            error = _error_mm(shapes[a], shapes[b])
            for name, radius in RADII_CM.items():
                reach = float(influence_reach(radius, FALLOFF_PER_CM, rig.model.clamp))
                still = nearest > reach
                floors[name].append(float(np.where(still, error, 0.0).mean()))
                unreached[name].append(float(still.mean()))
        table[str(n)] = {
            name: {
                "floor_mm": float(np.mean(floors[name])),
                "unreached_percent": 100 * float(np.mean(unreached[name])),
            }
            for name in RADII_CM
        }
        progress(f"  floor, {n} handles: {table[str(n)]}")
    return table


def _cell(direct, fitted, fitted_vertices, own_direct) -> dict:
    """One Table 4 cell from per-pair mean errors (mm; the first pairs fitted too), the
    fitted pairs' per-vertex errors and each fit's own direct error (``FitSolution``'s
    ``direct_error``, its start evaluated inside the fit's compiled program).

    ``fitted_never_worse`` is the library's guarantee, fitted <= its own direct error
    (exact); against the separate direct pass the two compiled programs round differently,
    so the largest excess over it is reported beside (float32 rounding, ~1e-6 mm)."""
    direct = np.asarray(direct, np.float64)
    fitted = np.asarray(fitted, np.float64)
    n_fitted = len(fitted)
    return {
        "direct_mm": float(direct.mean()),
        "fitted_mm": float(fitted.mean()),
        "fitted_p95_mm": float(np.percentile(np.concatenate(fitted_vertices), 95)),
        "direct_on_fitted_pairs_mm": float(direct[:n_fitted].mean()),
        "fitted_never_worse": bool(np.all(fitted <= np.asarray(own_direct))),
        "fitted_excess_over_direct_pass_max_mm": float(
            np.max(fitted - direct[:n_fitted], initial=0.0)
        ),
        "pairs_direct": len(direct),
        "pairs_fitted": n_fitted,
    }


def a_to_b_table(rig, shapes, pairs, placements, n_fit, options, progress=print, n_fit_main=0):
    """{handles: {radius name: {direct_mm, fitted_mm, fitted_p95_mm, ...}}} for one handle
    placement protocol (``placements(pair index, n) -> Handles``); the first ``n_fit`` pairs
    are fitted too (``n_fit_main`` at 200 handles / 2 cm, the issue's target cell)."""
    table = {}
    for n in HANDLE_COUNTS:
        table[str(n)] = {}
        cells = {
            name: {"direct": [], "fitted": [], "fitted_vertices": [], "own_direct": []}
            for name in RADII_CM
        }
        for p, (a, b) in enumerate(pairs):
            handles = placements(p, n)
            for name, radius in RADII_CM.items():
                direct = pose_a_to_b(rig, handles, shapes[a], shapes[b], radius, FALLOFF_PER_CM)
                cells[name]["direct"].append(float(direct.error) * CM_TO_MM)
                main_cell = n == 200 and name == "medium"
                if p < (max(n_fit, n_fit_main) if main_cell else n_fit):
                    fitted = pose_a_to_b(
                        rig,
                        handles,
                        shapes[a],
                        shapes[b],
                        radius,
                        FALLOFF_PER_CM,
                        fit=True,
                        options=options,
                    )
                    cells[name]["fitted"].append(float(fitted.error) * CM_TO_MM)
                    cells[name]["own_direct"].append(float(fitted.direct_error) * CM_TO_MM)
                    cells[name]["fitted_vertices"].append(_error_mm(fitted.shape, shapes[b]))
            if (p + 1) % 100 == 0:
                progress(f"  {n} handles: {p + 1}/{len(pairs)} pairs")
        for name, cell in cells.items():
            table[str(n)][name] = _cell(**cell)
        progress(
            f"  {n} handles: "
            + ", ".join(
                f"{k} {v['direct_mm']:.3f} -> {v['fitted_mm']:.3f} mm"
                for k, v in table[str(n)].items()
            )
        )
    return table


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, help="CANRig checkpoint (--rig network)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="a few pairs, short clips")
    parser.add_argument("--pairs", type=int, default=1000, help="(A, B) pairs, direct")
    parser.add_argument("--fit-pairs", type=int, default=1000, help="the first N pairs fitted")
    parser.add_argument(
        "--fit-pairs-main", type=int, default=0, help="more fitted pairs at 200 handles / 2 cm"
    )
    parser.add_argument("--layer-pairs", type=int, default=50)
    parser.add_argument("--fit-steps", type=int, default=FitOptions().max_steps)
    parser.add_argument("--lsmr-steps", type=int, default=FitOptions().lsmr_steps)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--dialogue-only",
        action="store_true",
        help="re-run only the dialogue replacement and its Table 6 baselines, updating "
        "--out/results.json, table.md and dialogue.png (the rest is kept)",
    )
    parser.add_argument(
        "--rig",
        choices=("network", "local-fit"),
        default="network",
        help="network: the CANRig checkpoint; local-fit: canrig.LocalFitRig, a rig with no "
        "network (local patch-blendshape fits, beyond the paper), its patches, basis and "
        "ridge selected on pairs of training poses, every workflow run on it unchanged",
    )
    parser.add_argument(
        "--floor-only",
        action="store_true",
        help="compute only the floor of Table 4's random-vertex protocol (error at vertices "
        "no handle reaches) into --out/results.json and table.md (the rest is kept)",
    )
    args = parser.parse_args(argv)
    if args.rig == "network" and args.checkpoint is None:
        parser.error("--checkpoint: required with --rig network")
    if args.quick:
        args.pairs, args.fit_pairs, args.layer_pairs = 4, 2, 2
    options = FitOptions(max_steps=args.fit_steps, lsmr_steps=args.lsmr_steps)
    start_time = time.perf_counter()

    quartic, _ = ict_quartic_rig(args.data_dir, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(quartic.names, missing="zero")
    _, capture_test = split_capture(capture)
    poses = held_out_poses(capture_test, quartic.names, n_random=100)
    shapes = evaluate_poses(quartic, poses)
    neutral = np.asarray(quartic.neutral, np.float32)
    if args.rig == "local-fit":
        rig, model_protocol = select_local_fit(quartic, capture, args)
    else:
        model, state = load_model(args.checkpoint, neutral)
        rig = NeuralRig(model, neutral, np.asarray(quartic.faces))
        model_protocol = {
            "checkpoint": str(args.checkpoint),
            "train_steps": state["step"],
            "train_minutes": state["seconds"] / 60.0,
            "p_farthest": state["options"]["examples"]["p_farthest"],
            "p_eval_radius": state["options"]["examples"]["p_eval_radius"],
        }
    if args.dialogue_only:
        return _dialogue_only(args, argv, rig, quartic, capture, options)
    pairs, random_sets, handle_rng = _random_protocol(len(shapes), rig.n_vertices, args)
    if args.floor_only:
        return _floor_only(args, argv, rig, shapes, pairs, random_sets)
    n_fit = min(args.fit_pairs, args.pairs)

    # ---------------------------------------------------------------- Table 4, A to B
    geodesic = {
        n: rig.handles(
            farthest_point_vertices(neutral, n, graph=rig.graph), limit=DISTANCE_LIMIT_CM
        )
        for n in HANDLE_COUNTS
    }
    print(f"A to B: {args.pairs} pairs ({n_fit} fitted), random vertices")
    a_to_b = {
        "random_vertices": a_to_b_table(
            rig,
            shapes,
            pairs,
            lambda p, n: rig.handles(random_sets[n][p], limit=DISTANCE_LIMIT_CM),
            n_fit,
            options,
            n_fit_main=min(args.fit_pairs_main, args.pairs),
        ),
    }
    print("A to B: geodesic farthest-point handles")
    a_to_b["geodesic_farthest"] = a_to_b_table(
        rig, shapes, pairs, lambda p, n: geodesic[n], n_fit, options
    )

    # ---------------------------------------------------------------- layers (Figure 15)
    layer_errors = {"direct": [], "fitted": []}
    for a, b in pairs[: args.layer_pairs]:
        schedule = [
            (rig.handles(handle_rng.choice(rig.n_vertices, n, replace=False)), radius)
            for n, radius in LAYER_SCHEDULE
        ]
        for kind in layer_errors:
            result = iterative_layers(
                rig,
                shapes[a],
                shapes[b],
                schedule,
                FALLOFF_PER_CM,
                fit=kind == "fitted",
                options=options,
            )
            layer_errors[kind].append(result.errors * CM_TO_MM)
    layers = {f"{k}_mm": np.mean(v, axis=0).tolist() for k, v in layer_errors.items()}
    fitted_layers = np.array(layer_errors["fitted"])
    layers["fitted_non_increasing_every_pair"] = bool(np.all(np.diff(fitted_layers, axis=1) <= 0))
    layers["pairs"] = len(fitted_layers)
    print(f"layers: direct {layers['direct_mm']}, fitted {layers['fitted_mm']}")

    # ---------------------------------------------------------------- clip edit (Figure 10)
    clip_weights = capture_test[:30] if args.quick else capture_test
    clip = evaluate_poses(quartic, clip_weights)
    frame = len(clip) // 2
    mouth = expression_region(quartic, threshold=MOUTH_THRESHOLD_CM)
    jaw = list(quartic.names).index("jawOpen")
    wider = clip_weights[frame].copy()
    wider[jaw] = min(1.0, wider[jaw] + 0.3)
    wider_shape = evaluate_poses(quartic, wider[None])[0]
    moved = np.linalg.norm(wider_shape - clip[frame], axis=1)
    mouth_chin = np.flatnonzero(mouth & (moved > 0.05))  # the vertices the edit moves > 0.5 mm
    clip_index = mouth_chin[
        farthest_point_vertices(
            neutral[mouth_chin], CLIP_HANDLES, start=int(np.argmax(moved[mouth_chin]))
        )
    ]
    clip_handles = rig.handles(clip_index)
    solution = pose_a_to_b(
        rig,
        clip_handles,
        clip[frame],
        wider_shape,
        CLIP_RADIUS_CM,
        FALLOFF_PER_CM,
        fit=True,
        region=mouth,
        options=options,
    )
    edited = clip_edit(
        rig,
        clip,
        frame,
        clip_handles,
        np.asarray(solution.displacements),
        CLIP_RADIUS_CM,
        FALLOFF_PER_CM,
        CLIP_HALF_WINDOW,
    )
    lo, hi = edited.window
    outside_window = np.r_[0:lo, hi + 1 : len(clip)]
    clip_mask = np.asarray(
        influence_mask(clip_handles.distance, CLIP_RADIUS_CM, FALLOFF_PER_CM, rig.model.clamp)
    )
    outside_mask = clip_mask.max(axis=1) == 0
    clip_numbers = {
        "outside_window_max_mm": float(
            _error_mm(edited.clip[outside_window], clip[outside_window]).max(initial=0.0)
        ),
        "outside_window_bit_identical": bool(
            np.array_equal(edited.clip[outside_window], clip[outside_window])
        ),
        "outside_mask_max_mm": float(_error_mm(edited.clip, clip)[:, outside_mask].max()),
        "edit_error_mm": float(_error_mm(edited.clip[frame], wider_shape)[mouth].mean()),
        "edit_error_before_mm": float(_error_mm(clip[frame], wider_shape)[mouth].mean()),
        "max_acceleration_before": max_acceleration(clip) * CM_TO_MM,
        "max_acceleration_after": max_acceleration(edited.clip) * CM_TO_MM,
        "max_acceleration_of_the_edit": max_acceleration(edited.clip - clip) * CM_TO_MM,
        "frame": int(frame),
        "window": [int(lo), int(hi)],
        "handles": CLIP_HANDLES,
        "radius_cm": CLIP_RADIUS_CM,
        "outside_mask_vertices": int(outside_mask.sum()),
    }
    print(f"clip edit: {clip_numbers}")

    # ---------------------------------------------------------------- dialogue (Figure 12)
    dialogue_results, dialogue_run = dialogue_table(
        rig, quartic, capture, mouth, options, 6 if args.quick else 45, args.seed
    )
    source, target, dialogue_handles = (
        dialogue_run["source"],
        dialogue_run["target"],
        dialogue_run["handles"],
    )
    outputs = dialogue_run["outputs"]

    # ---------------------------------------------------------------- timing
    a, b = shapes[pairs[0, 0]], shapes[pairs[0, 1]]
    h200 = rig.handles(random_sets[200][0], limit=DISTANCE_LIMIT_CM)

    def run(fit):
        return pose_a_to_b(rig, h200, a, b, 2.0, FALLOFF_PER_CM, fit=fit, options=options)

    timing = {
        "direct_ms_200_handles": _timed(lambda: run(False).shape.block_until_ready()),
        "fit_ms_200_handles": _timed(lambda: run(True).shape.block_until_ready(), repeats=3),
        "dialogue_ms_per_frame": _timed(
            lambda: dialogue_replacement(
                rig, source, target, dialogue_handles, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM
            ),
            repeats=3,
        )
        / len(source),
    }
    print(f"timing: {timing}")

    results = {
        "a_to_b": a_to_b,
        "layers": layers,
        "clip_edit": clip_numbers,
        "dialogue": dialogue_results,
        "timing": timing,
        "protocol": {
            "pairs": args.pairs,
            "seed": args.seed,
            "fitted_pairs": n_fit,
            "held_out_poses": {"capture_frames": len(capture_test), "random_poses": 100},
            "falloff_per_cm": FALLOFF_PER_CM,
            "radii_cm": RADII_CM,
            "fit_options": {"max_steps": options.max_steps, "lsmr_steps": options.lsmr_steps},
            "model": model_protocol,
        },
        "minutes": (time.perf_counter() - start_time) / 60.0,
    }
    results["provenance"] = provenance(experiment_command(__file__, argv))
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    table = _table(results)
    save_text(args.out / "table.md", table)
    _figure_a_to_b(
        rig, shapes, pairs[0], random_sets[200][0], options, args.out / "a_to_b_error.png"
    )
    _figure_layers(layer_errors, args.out / "layers.png")
    _figure_clip(clip, edited, frame, wider_shape, args.out / "clip_edit.png")
    _figure_dialogue(
        rig, source, target, outputs["direct"], mouth, dialogue_handles, args.out / "dialogue.png"
    )
    print(table)
    print(f"wrote {args.out}/results.json, table.md and figures")
    return results


def dialogue_table(rig, quartic, capture, mouth, options, n_dialogue, seed):
    """Dialogue replacement (Figure 12 / Table 6): CANRig direct and fitted in the mouth
    mask, and the global-blendshape baseline (GBS) with the 19-shape basis and with ICT's 53
    expressions: each source frame inverted by a fit at 200 handles over the face, then
    refitted with the mouth handles at the target frame."""
    neutral = np.asarray(quartic.neutral, np.float32)
    source = evaluate_poses(quartic, capture[90 : 90 + n_dialogue])
    target = evaluate_poses(quartic, capture[135 : 135 + n_dialogue])
    reach = float(influence_reach(DIALOGUE_RADIUS_CM, FALLOFF_PER_CM, rig.model.clamp))
    interior = interior_vertices(rig, mouth, reach)
    dialogue_index = interior[farthest_point_vertices(neutral[interior], DIALOGUE_HANDLES)]
    dialogue_handles = rig.handles(dialogue_index)
    dialogue, outputs = {}, {}
    for kind in ("direct", "fitted"):
        out = dialogue_replacement(
            rig,
            source,
            target,
            dialogue_handles,
            DIALOGUE_RADIUS_CM,
            FALLOFF_PER_CM,
            fit=kind == "fitted",
            region=mouth,
            options=options,
        )
        outputs[kind] = out
        dialogue[kind] = {
            "mouth_difference_mm": float(_error_mm(out, target)[:, mouth].mean()),
            "rest_of_face_change_mm": float(_error_mm(out, source)[:, ~mouth].max()),
        }
    zero = dialogue_replacement(
        rig, source, source, dialogue_handles, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM
    )
    # GBS: the same 60 mouth handles, moved, plus 140 geodesic farthest points off the mouth
    # (still), so that the inversion of each frame sees the whole face
    off_mouth = np.flatnonzero(~mouth)
    still = off_mouth[farthest_point_vertices(neutral[off_mouth], 200 - DIALOGUE_HANDLES)]
    gbs_index = np.concatenate([dialogue_index, still])
    moved = np.arange(len(gbs_index)) < DIALOGUE_HANDLES
    training = random_sparse_poses(np.random.default_rng([seed, 2]), 200, quartic.names)
    basis_19, _ = pbs_basis(neutral, evaluate_poses(quartic, training), 19)
    baselines = {}
    for name, basis in (("gbs_19", basis_19), ("gbs_ict_53", np.asarray(quartic.deltas))):
        inverted, edited = global_blendshape_dialogue(
            basis, neutral, source, target, gbs_index, moved
        )
        inverted, edited = np.asarray(inverted), np.asarray(edited)
        baselines[name] = {
            "rig_inversion_mm": float(_error_mm(inverted, source).mean()),
            "mouth_difference_mm": float(_error_mm(edited, target)[:, mouth].mean()),
            "rest_of_face_change_mm": float(_error_mm(edited, source)[:, ~mouth].mean()),
            "rest_of_face_change_max_mm": float(_error_mm(edited, source)[:, ~mouth].max()),
        }
    results = {
        "rig_inversion_mm": float(_error_mm(zero, source).max()),
        "mouth_difference_mm": dialogue["direct"]["mouth_difference_mm"],
        "rest_of_face_change_mm": dialogue["direct"]["rest_of_face_change_mm"],
        "fitted": dialogue["fitted"],
        "baselines": baselines,
        "baseline_protocol": "GBS (CANRig Table 6): basis offsets fitted by ridge least squares "
        "(1e-3 x the mean diagonal) at 200 handles: the 60 mouth handles (moved to the target "
        "frame) and 140 geodesic farthest points off the mouth mask (kept at the source); "
        "gbs_19: the neutral + 18 farthest-point shapes of 200 random sparse poses (not the "
        "held-out ones); gbs_ict_53: the rig's 53 linear expressions. Means over frames and "
        "vertices (rest of face: mean, and its max beside it); CANRig's inversion and rest of "
        "face are maxima (0.0)",
        "source_mouth_difference_mm": float(_error_mm(source, target)[:, mouth].mean()),
        "frames": {"source": [90, 89 + n_dialogue], "target": [135, 134 + n_dialogue]},
        "mouth_mask_vertices": int(mouth.sum()),
        "mouth_mask": f"expression_region(threshold={MOUTH_THRESHOLD_CM} cm): vertices some "
        "jaw*/mouth* expression of the ict-quartic rig moves more than that and no eye*/brow* "
        "expression does",
        "handles": DIALOGUE_HANDLES,
        "radius_cm": DIALOGUE_RADIUS_CM,
    }
    print(f"dialogue: {results}")
    run = {"source": source, "target": target, "handles": dialogue_handles, "outputs": outputs}
    return results, run


def _results_of_the_same_pairs(args, flag):
    """OUT's results.json, checked to hold Table 4 with this run's --pairs and --seed."""
    results = json.loads((args.out / "results.json").read_text())
    protocol = results["protocol"]
    if (protocol["pairs"], protocol.get("seed", 0)) != (args.pairs, args.seed):
        raise ValueError(
            f"{flag}: pass the --pairs and --seed of {args.out}/results.json "
            f"({protocol['pairs']}, {protocol.get('seed', 0)}; the seed was 0 before it was "
            "recorded)"
        )
    return results


def _floor_only(args, argv, rig, shapes, pairs, random_sets):
    results = _results_of_the_same_pairs(args, "--floor-only")
    results["a_to_b_floor"] = {
        "random_vertices": unreached_floor(rig, np.asarray(shapes), pairs, random_sets)
    }
    results["a_to_b_floor_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(args.out / "results.json", results)
    table = _table(results)
    save_text(args.out / "table.md", table)
    print(table)
    return results


LOCAL_FIT_GRID = {"patches": (300, 600), "basis": (19, 40, 60), "ridge": (1e-4, 1e-3, 1e-2)}


def select_local_fit(quartic, capture, args):
    """``--rig local-fit``: the ``LocalFitRig`` on the face whose patch count, basis size and
    ridge give the lowest direct error at 200 random handles / 2 cm on pairs of the network's
    *training* poses (never the held-out ones); the basis is ``pbs_basis`` of those poses.
    Returns (NeuralRig, the protocol's model entry with the whole selection)."""
    capture_train, _ = split_capture(capture)
    train = np.concatenate(
        [
            capture_train,
            random_sparse_poses(np.random.default_rng(0), 800, quartic.names, n_active=(4, 10)),
        ]
    ).astype(np.float32)  # the training poses of build_training_set (seed 0)
    train_shapes = np.asarray(evaluate_poses(quartic, train))
    neutral, faces = np.asarray(quartic.neutral, np.float32), np.asarray(quartic.faces)
    rng = np.random.default_rng([args.seed, 7])
    select_pairs = _pairs(len(train_shapes), 4 if args.quick else 30, rng)
    select_sets = [rng.choice(len(neutral), 200, replace=False) for _ in select_pairs]
    selection, best, handles = [], None, None
    for n_patches in LOCAL_FIT_GRID["patches"]:
        layout = patch_layout(neutral, faces, n_patches, rings=3)
        for n_basis in LOCAL_FIT_GRID["basis"]:
            basis, _ = pbs_basis(neutral, train_shapes, n_basis)
            for ridge in LOCAL_FIT_GRID["ridge"]:
                rig = NeuralRig(local_fit_rig(layout, basis, ridge), neutral, faces)
                if handles is None:  # the same placements (geodesic distances) for every rig
                    handles = [rig.handles(h, limit=DISTANCE_LIMIT_CM) for h in select_sets]
                errors = [
                    pose_a_to_b(rig, h, train_shapes[a], train_shapes[b], 2.0, FALLOFF_PER_CM).error
                    for (a, b), h in zip(select_pairs, handles, strict=True)
                ]
                row = {
                    "patches": n_patches,
                    "basis": n_basis,
                    "ridge": ridge,
                    "mm": float(np.mean(errors)) * CM_TO_MM,
                }
                selection.append(row)
                print(f"  selection on training pairs: {row}")
                if best is None or row["mm"] < best[0]["mm"]:
                    best = (row, rig)
    chosen, rig = best
    protocol = {
        "rig": "canrig.LocalFitRig (no network): per patch a ridge fit of the basis offsets "
        "to the handle displacements its clamped masks see (at the patch seed), blended by the "
        "layout, each vertex scaled by min(1, 2 x its largest clamped mask); basis: pbs_basis "
        "(farthest points in shape space) of the network's training shapes; fitted: "
        "FitOptions.max_steps "
        "LSMR iterations from the direct displacements",
        "selected": chosen,
        "selection_on_training_pairs": selection,
    }
    return rig, protocol


def _dialogue_only(args, argv, rig, quartic, capture, options):
    results = json.loads((args.out / "results.json").read_text())
    mouth = expression_region(quartic, threshold=MOUTH_THRESHOLD_CM)
    n = 6 if args.quick else 45
    results["dialogue"], run = dialogue_table(rig, quartic, capture, mouth, options, n, args.seed)
    results["dialogue_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(args.out / "results.json", results)
    table = _table(results)
    save_text(args.out / "table.md", table)
    _figure_dialogue(
        rig,
        run["source"],
        run["target"],
        run["outputs"]["direct"],
        mouth,
        run["handles"],
        args.out / "dialogue.png",
    )
    print(table)
    return results


def _a_to_b_rows(table) -> list[str]:
    """Table 4's Markdown rows (handles x radius) for one ``a_to_b_table``-like dict."""
    lines = [
        "| handles | " + " | ".join(f"{k} ({v:g} cm)" for k, v in RADII_CM.items()) + " |",
        "|---" * (len(RADII_CM) + 1) + "|",
    ]
    for n, row in table.items():
        cells = [
            f"{c['direct_mm']:.3f} / {c['direct_on_fitted_pairs_mm']:.3f} / "
            f"**{c['fitted_mm']:.3f}** / {c['fitted_p95_mm']:.2f} ({c['pairs_fitted']})"
            for c in row.values()
        ]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _model_line(model):
    if "selected" in model:
        chosen = model["selected"]
        return (
            "Rig: `LocalFitRig`, no network (beyond the paper): "
            f"{chosen['patches']} patches, neutral + {chosen['basis'] - 1} basis offsets, "
            f"ridge {chosen['ridge']:g}, selected on pairs of training poses."
        )
    trained_on = (
        "random handle sets and radii (the paper's recipe)"
        if model["p_farthest"] == 0 and model["p_eval_radius"] == 0
        else f"{model['p_farthest']:.0%} evaluation handle sets, {model['p_eval_radius']:.0%} "
        "evaluation radii"
    )
    return f"Model trained on {trained_on}, {model['train_steps']} steps."


def _table(results):
    lines = [
        f"Pose A to pose B (Table 4 protocol): {results['protocol']['pairs']} random pairs of "
        f"held-out ict-quartic poses (fitted on the first {results['protocol']['fitted_pairs']}), "
        f"mean per-vertex error to B over the 9,409 face vertices (mm), falloff 3/cm. "
        + _model_line(results["protocol"]["model"]),
        "",
    ]
    for protocol, table in results["a_to_b"].items():
        lines += [
            f"**{protocol}**: direct (all pairs) / direct on the fitted pairs / **fitted** / "
            "fitted p95 (mm); fitted pairs per cell in brackets",
            "",
        ]
        lines += _a_to_b_rows(table)
    floor = results.get("a_to_b_floor", {}).get("random_vertices")
    if floor:
        lines += [
            "**Floor of any result, random_vertices** (mm; vertices beyond every handle's "
            "reach keep A's position whatever the network or the fit; % of vertices unreached "
            "in brackets)",
            "",
            "| handles | " + " | ".join(f"{k} ({v:g} cm)" for k, v in RADII_CM.items()) + " |",
            "|---" * (len(RADII_CM) + 1) + "|",
        ]
        for n, row in floor.items():
            cells = [f"{c['floor_mm']:.3f} ({c['unreached_percent']:.1f} %)" for c in row.values()]
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        lines.append("")
    layers = results["layers"]
    clip, dialogue, timing = results["clip_edit"], results["dialogue"], results["timing"]
    rows = [
        (
            "layers 20/4cm, 75/2cm, 200/1cm, direct (mm)",
            " / ".join(f"{x:.3f}" for x in layers["direct_mm"]),
        ),
        ("layers, fitted (mm)", " / ".join(f"{x:.3f}" for x in layers["fitted_mm"])),
        ("fitted layers non-increasing on every pair", layers["fitted_non_increasing_every_pair"]),
        (
            "clip edit: outside window max (mm); bit-identical",
            f"{clip['outside_window_max_mm']:g}; {clip['outside_window_bit_identical']}",
        ),
        ("clip edit: outside every clamped mask max (mm)", f"{clip['outside_mask_max_mm']:g}"),
        (
            "clip edit: mouth error to the target at the frame, before -> after (mm)",
            f"{clip['edit_error_before_mm']:.3f} -> {clip['edit_error_mm']:.3f}",
        ),
        (
            "clip: max acceleration before / after / of the edit alone (mm/frame^2)",
            " / ".join(
                f"{clip[k]:.3f}"
                for k in ("max_acceleration_before", "max_acceleration_after")
                + ("max_acceleration_of_the_edit",)
            ),
        ),
        ("dialogue: rig inversion (mm)", f"{dialogue['rig_inversion_mm']:g}"),
        (
            "dialogue: mouth difference, direct / fitted / no edit (mm)",
            " / ".join(
                f"{x:.3f}"
                for x in (
                    dialogue["mouth_difference_mm"],
                    dialogue["fitted"]["mouth_difference_mm"],
                    dialogue["source_mouth_difference_mm"],
                )
            ),
        ),
        (
            "dialogue: rest of face change, direct / fitted (mm)",
            f"{dialogue['rest_of_face_change_mm']:g} / "
            f"{dialogue['fitted']['rest_of_face_change_mm']:g}",
        ),
        ("fitted A to B, 200 handles, 2 cm (ms, one call)", f"{timing['fit_ms_200_handles']:.0f}"),
        (
            "direct A to B, 200 handles, 2 cm (ms, one call)",
            f"{timing['direct_ms_200_handles']:.1f}",
        ),
        (
            "dialogue replacement, batched over the clip (ms per frame)",
            f"{timing['dialogue_ms_per_frame']:.1f}",
        ),
    ]
    lines += ["| quantity | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows]
    baselines = dialogue.get("baselines")
    rig_name = "LocalFitRig" if "selected" in results["protocol"]["model"] else "CANRig"
    if baselines:
        lines += [
            "",
            "Dialogue replacement as Table 6 (mm; CANRig's inversion and rest of face are "
            "maxima, the baselines' means with the max in brackets)",
            "",
            "| method | rig inversion | mouth difference | rest of face change |",
            "|---|---|---|---|",
        ]
        for kind, numbers in (("direct", dialogue), ("fitted", dialogue["fitted"])):
            lines.append(
                f"| {rig_name}, {kind} | {dialogue['rig_inversion_mm']:g} | "
                f"{numbers['mouth_difference_mm']:.3f} | {numbers['rest_of_face_change_mm']:g} |"
            )
        for name, b in baselines.items():
            lines.append(
                f"| {name} | {b['rig_inversion_mm']:.3f} | {b['mouth_difference_mm']:.3f} | "
                f"{b['rest_of_face_change_mm']:.3f} ({b['rest_of_face_change_max_mm']:.2f}) |"
            )
    return "\n".join(lines) + "\n"


def _error_panels(faces, b, panels, vmax, title, path):
    """One row of per-vertex error maps to B (mm), each panel (name, shape)."""
    fig, axes = plt.subplots(1, len(panels), figsize=(10, 4.2))
    for ax, (name, shape) in zip(axes, panels, strict=True):
        err = _error_mm(shape, b)
        mapper = plot_vertex_scalar(
            ax, np.asarray(shape), faces, err, vmax=vmax, title=name.format(mean=err.mean())
        )
    fig.suptitle(title)
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="per-vertex error to B (mm)")
    save_figure(fig, path)


def _figure_a_to_b(rig, shapes, pair, index, options, path):
    a, b = shapes[pair[0]], shapes[pair[1]]
    handles = rig.handles(index, limit=DISTANCE_LIMIT_CM)
    direct = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM)
    fitted = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM, fit=True, options=options)
    _error_panels(
        rig.faces,
        b,
        [
            ("pose A (error to B)", a),
            ("direct: mean {mean:.2f} mm", direct.shape),
            ("fitted: mean {mean:.2f} mm", fitted.shape),
        ],
        10.0,
        "pose A to pose B, 200 random-vertex handles, radius 2 cm (Figure 9 analog)",
        path,
    )


def _figure_layers(layer_errors, path):
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for kind, errors in layer_errors.items():
        errors = np.array(errors)
        normalised = errors / errors[:, :1]
        ax.plot(np.arange(1, errors.shape[1] + 1), normalised.mean(axis=0), "o-", label=kind)
    ax.set_xticks([1, 2, 3], [f"{n} / {r:g} cm" for n, r in LAYER_SCHEDULE])
    ax.set_ylabel("error / first layer's error")
    ax.set_title("iterative layers (Figure 15 analog)")
    ax.legend()
    save_figure(fig, path)


def _figure_clip(clip, edited, frame, wider_shape, path):
    """Mouth opening over time: the vertical gap between the lowest upper-lip-region vertex
    and the chin's most-moved vertex (a proxy: the vertex the jawOpen edit moves most)."""
    moved = np.linalg.norm(wider_shape - clip[frame], axis=1)
    chin = int(np.argmax(moved))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    frames = np.arange(len(clip))
    ax.plot(frames, clip[:, chin, 1] * CM_TO_MM, label="input clip")
    ax.plot(frames, edited.clip[:, chin, 1] * CM_TO_MM, label="edited clip")
    ax.axvline(frame, color="grey", lw=0.5)
    ax.set_xlabel("frame (held-out capture half)")
    ax.set_ylabel("height of the most-moved chin vertex (mm)")
    twin = ax.twinx()
    twin.plot(frames, edited.fade, "k--", lw=0.8, label="fade weight")
    twin.set_ylabel("fade weight")
    ax.legend(loc="lower left")
    ax.set_title("clip edit: jaw opened wider at one frame, faded over ±10 frames")
    save_figure(fig, path)


def _figure_dialogue(rig, source, target, out, mouth, handles, path):
    f = len(source) // 2
    fig, axes = plt.subplots(1, 4, figsize=(13, 4.2))
    plot_vertex_scalar(
        axes[0],
        source[f],
        rig.faces,
        mouth.astype(float),
        vmax=1.0,
        cmap="viridis",
        title="source frame, mouth mask",
    )
    axes[0].scatter(*source[f][handles.index][:, :2].T, s=4, c="red")
    plot_vertex_scalar(
        axes[1],
        target[f],
        rig.faces,
        _error_mm(target[f], source[f]),
        vmax=10.0,
        title="target frame (vs source)",
    )
    plot_vertex_scalar(
        axes[2],
        out[f],
        rig.faces,
        _error_mm(out[f], target[f]),
        vmax=10.0,
        title="replaced (error to target)",
    )
    mapper = plot_vertex_scalar(
        axes[3],
        out[f],
        rig.faces,
        _error_mm(out[f], source[f]),
        vmax=10.0,
        title="change from source",
    )
    fig.colorbar(mapper, ax=axes[1:], shrink=0.7, label="mm")
    fig.suptitle("dialogue replacement (Figure 12 analog): handles in red")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
