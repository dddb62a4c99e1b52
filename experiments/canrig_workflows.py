"""CANRig workflows on real data: pose A to B (direct and fitted), iterative layers and clip
editing on the ict-quartic rig.

    python experiments/canrig_workflows.py \
        --checkpoint experiments/results/canrig_workflows/model/checkpoint.eqx \
        --out experiments/results/canrig_workflows

Held-out poses: the Live Link capture's second half (frames 90-179) and 100 random sparse
poses (``canrig.held_out_poses``, as ``canrig_eval.py``). Table 4 as the paper runs it: random
(A, B) pairs of held-out poses, A != B, handles at random vertices (a new set per pair),
20/75/200 handles x 1/2/4 cm, falloff 3/cm, the error of the result against B averaged over
all 9,409 face vertices. Geodesic farthest-point handles from vertex 0 (``canrig_eval.py``'s
placement) are reported beside it as a second protocol. Writes results.json, table.md and
figures (a_to_b_error.png, layers.png, clip_edit.png). The protocols are
``canrig_jax.papers.canrig.workflows``.

Then, into the same folder: ``canrig_workflows_dialogue.py`` (dialogue replacement and its
Table 6 baselines) and ``canrig_workflows_floor.py`` (the floor of Table 4's random-vertex
protocol).

``--rig local-fit`` runs every workflow on ``canrig.LocalFitRig``, a rig with no network
(beyond the paper), instead of the checkpoint:

    python experiments/canrig_workflows.py --rig local-fit \
        --out experiments/results/canrig_workflows_local_fit
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax._timing import median_ms
from canrig_jax.canrig import FitOptions, pose_a_to_b
from canrig_jax.mesh import farthest_point_vertices
from canrig_jax.papers.canrig import RADII_CM
from canrig_jax.papers.canrig.workflows import (
    DISTANCE_LIMIT_CM,
    FALLOFF_PER_CM,
    HANDLE_COUNTS,
    LAYER_SCHEDULE,
    a_to_b_table,
    clip_edit_protocol,
    layers_protocol,
    network_rig,
    select_local_fit,
    table4_protocol,
    workflow_data,
    workflows_markdown,
)
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.watchdog import run_watched


def _parser() -> argparse.ArgumentParser:
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
        "--rig",
        choices=("network", "local-fit"),
        default="network",
        help="network: the CANRig checkpoint; local-fit: canrig.LocalFitRig, a rig with no "
        "network (local patch-blendshape fits, beyond the paper), its patches, basis and "
        "ridge selected on pairs of training poses, every workflow run on it unchanged",
    )
    return parser


def _table4(rig, shapes, pairs, random_sets, options, args) -> dict:
    """Table 4 for both handle placements: random vertices (a new set per pair) and
    geodesic farthest points from vertex 0."""
    n_fit = min(args.fit_pairs, args.pairs)
    neutral = np.asarray(rig.canonical)
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
    return a_to_b


def _timing(rig, a, b, handles, options) -> dict:
    """One direct and one fitted A-to-B call at 200 handles / 2 cm (ms, median)."""

    def run(fit):
        return pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM, fit=fit, options=options).shape

    return {
        "direct_ms_200_handles": median_ms(lambda: run(False), repeats=5),
        "fit_ms_200_handles": median_ms(lambda: run(True), repeats=3),
    }


def main(argv=None):
    parser = _parser()
    args = parser.parse_args(argv)
    if args.rig == "network" and args.checkpoint is None:
        parser.error("--checkpoint: required with --rig network")
    if args.quick:
        args.pairs, args.fit_pairs, args.layer_pairs = 4, 2, 2
    options = FitOptions(max_steps=args.fit_steps, lsmr_steps=args.lsmr_steps)
    start_time = time.perf_counter()

    data = workflow_data(args.data_dir)
    quartic, shapes = data.quartic, data.shapes
    if args.rig == "local-fit":
        n_select = 4 if args.quick else 30
        rig, model_protocol = select_local_fit(
            quartic, data.capture, seed=args.seed, n_pairs=n_select
        )
    else:
        rig, model_protocol = network_rig(args.checkpoint, quartic)
    pairs, random_sets, handle_rng = table4_protocol(
        len(shapes), rig.n_vertices, args.pairs, args.seed
    )
    a_to_b = _table4(rig, shapes, pairs, random_sets, options, args)

    layers, layer_errors = layers_protocol(
        rig, shapes, pairs[: args.layer_pairs], handle_rng, options
    )
    print(f"layers: direct {layers['direct_mm']}, fitted {layers['fitted_mm']}")

    clip_weights = data.capture_test[:30] if args.quick else data.capture_test
    clip_numbers, clip_run = clip_edit_protocol(rig, quartic, clip_weights, options)
    print(f"clip edit: {clip_numbers}")

    h200 = rig.handles(random_sets[200][0], limit=DISTANCE_LIMIT_CM)
    timing = _timing(rig, shapes[pairs[0, 0]], shapes[pairs[0, 1]], h200, options)
    print(f"timing: {timing}")

    results = {
        "a_to_b": a_to_b,
        "layers": layers,
        "clip_edit": clip_numbers,
        "timing": timing,
        "protocol": {
            "pairs": args.pairs,
            "seed": args.seed,
            "fitted_pairs": min(args.fit_pairs, args.pairs),
            "held_out_poses": {"capture_frames": len(data.capture_test), "random_poses": 100},
            "falloff_per_cm": FALLOFF_PER_CM,
            "radii_cm": RADII_CM,
            "fit_options": {"max_steps": options.max_steps, "lsmr_steps": options.lsmr_steps},
            "model": model_protocol,
        },
        "minutes": (time.perf_counter() - start_time) / 60.0,
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    table = workflows_markdown(results)
    save_text(args.out / "table.md", table)
    _figure_a_to_b(
        rig, shapes, pairs[0], random_sets[200][0], options, args.out / "a_to_b_error.png"
    )
    _figure_layers(layer_errors, args.out / "layers.png")
    _figure_clip(clip_run, args.out / "clip_edit.png")
    print(table)
    print(f"wrote {args.out}/results.json, table.md and figures")
    return results


def _error_mm(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1) * CM_TO_MM


def _figure_a_to_b(rig, shapes, pair, index, options, path):
    """Per-vertex error to B of A, the direct and the fitted result (Figure 9 analog)."""
    a, b = shapes[pair[0]], shapes[pair[1]]
    handles = rig.handles(index, limit=DISTANCE_LIMIT_CM)
    direct = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM)
    fitted = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM, fit=True, options=options)
    panels = [
        ("pose A (error to B)", a),
        ("direct: mean {mean:.2f} mm", direct.shape),
        ("fitted: mean {mean:.2f} mm", fitted.shape),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(10, 4.2))
    for ax, (name, shape) in zip(axes, panels, strict=True):
        err = _error_mm(shape, b)
        mapper = plot_vertex_scalar(
            ax, np.asarray(shape), rig.faces, err, vmax=10.0, title=name.format(mean=err.mean())
        )
    fig.suptitle("pose A to pose B, 200 random-vertex handles, radius 2 cm (Figure 9 analog)")
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="per-vertex error to B (mm)")
    save_figure(fig, path)


def _figure_layers(layer_errors, path):
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for kind, errors in layer_errors.items():
        normalised = errors / errors[:, :1]
        ax.plot(np.arange(1, errors.shape[1] + 1), normalised.mean(axis=0), "o-", label=kind)
    ax.set_xticks([1, 2, 3], [f"{n} / {r:g} cm" for n, r in LAYER_SCHEDULE])
    ax.set_ylabel("error / first layer's error")
    ax.set_title("iterative layers (Figure 15 analog)")
    ax.legend()
    save_figure(fig, path)


def _figure_clip(run, path):
    """Mouth opening over time: the height of the chin's most-moved vertex (the vertex the
    jawOpen edit moves most), before and after the edit, and the fade weight."""
    clip, edited, frame = run.clip, run.edited, run.frame
    chin = int(np.argmax(np.linalg.norm(run.target - clip[frame], axis=1)))
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


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
