"""Evaluate a trained CANRig checkpoint on held-out ict-quartic shapes.

    python experiments/canrig_eval.py --checkpoint experiments/results/canrig/checkpoint.eqx \
        --out experiments/results/canrig

Held out: the second half of the Live Link capture and 100 random sparse poses drawn with
another seed. Handles: geodesic farthest-point sets from vertex 0 (the Euclidean sets of
earlier runs are reported beside them at 200 handles / medium). Writes results.json (the keys
of issue 5, plus context), table.md, mask_radii.png (the paper's Figure 4 analog) and
heldout_error.png (0-10 mm).
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._checkpoint import parameter_count
from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.canrig import CLAMP, NeuralRig, influence_mask, load_model
from canrig_jax.canrig._data import evaluate_poses
from canrig_jax.data import load_livelinkface
from canrig_jax.mesh import farthest_point_vertices
from canrig_jax.papers.canrig import EVAL_FALLOFF_PER_CM, RADII_CM, held_out_poses, split_capture
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import ict_quartic_rig
from canrig_jax.watchdog import run_watched

FALLOFF_PER_CM = EVAL_FALLOFF_PER_CM
HANDLE_COUNTS = (20, 75, 200)


def _runner(neural: NeuralRig):
    """Shapes for each (target, base) pair: displacements target - base at the handles,
    the library's block-sparse forward pass (exact; see canrig/blocks.py)."""

    def call(handles, targets, bases, radius, beta=0.0, dense=False):
        out = []
        for target, base in zip(targets, bases, strict=True):
            disp = target[handles.index] - base[handles.index]
            shape = neural(handles, disp, radius, FALLOFF_PER_CM, base=base, beta=beta, dense=dense)
            out.append(np.asarray(shape))
        return np.stack(out)

    return call


def _error_mm(a, b):
    return np.linalg.norm(a - b, axis=-1) * CM_TO_MM


def _interpolation_baseline(handles, targets, neutral, radius):
    """No network: each vertex moves by the mask-weighted mean of the handle displacements,
    sum_h M_h d_h / max(sum_h M_h, 1) with the same clamped masks (the model's interpolation
    prior alone)."""
    n = handles.n_handles
    mask = np.asarray(
        influence_mask(handles.distance, np.full(n, radius), np.full(n, FALLOFF_PER_CM), CLAMP)
    )
    weights = mask / np.maximum(mask.sum(axis=1, keepdims=True), 1.0)
    displacements = targets[:, handles.index] - neutral[handles.index]
    moved = neutral + np.einsum("vh,nhc->nvc", weights, displacements)
    return _error_mm(moved, targets)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="6 capture frames + 6 random poses")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)

    rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    _, capture_test = split_capture(capture)
    if args.quick:
        capture_test = capture_test[::15]
    poses = held_out_poses(
        capture_test, rig.names, n_random=6 if args.quick else 100, seed=args.seed
    )
    targets = evaluate_poses(rig, poses)
    neutral = np.asarray(rig.neutral, np.float32)
    faces = np.asarray(rig.faces)
    model, state = load_model(args.checkpoint, neutral)
    neural = NeuralRig(model, neutral, faces)
    run = _runner(neural)
    neutrals = np.broadcast_to(neutral, targets.shape)

    # handles: farthest-point sets from vertex 0, geodesic (the metric of the masks); the
    # Euclidean placement of earlier runs is reported beside it at 200 handles
    placed = {
        n: neural.handles(farthest_point_vertices(neutral, n, graph=neural.graph))
        for n in HANDLE_COUNTS
    }
    h200 = placed[200]
    euclidean_h200 = neural.handles(farthest_point_vertices(neutral, 200))

    # exact properties
    bases = np.concatenate([neutral[None], targets[:: max(1, len(targets) // 4)][:4]])
    zero_max = 0.0
    for radius in RADII_CM.values():
        out = run(h200, bases, bases, radius)  # targets == bases: zero displacements
        zero_max = max(zero_max, float(np.abs(out - bases).max()) * CM_TO_MM)
    small = RADII_CM["small"]
    outside_max, outside_count = 0.0, 0
    for n in HANDLE_COUNTS:
        out = run(placed[n], targets[: len(bases)], bases, small)
        mask = np.asarray(
            influence_mask(placed[n].distance, np.full(n, small), np.full(n, FALLOFF_PER_CM), CLAMP)
        )
        outside = mask.max(axis=1) == 0.0
        outside_count = max(outside_count, int(outside.sum()))
        outside_max = max(
            outside_max,
            float(np.abs(out[:, outside] - bases[:, outside]).max(initial=0.0)) * CM_TO_MM,
        )

    # the block-sparse forward pass against the dense one
    few = targets[:3]
    blocked_vs_dense = float(
        np.abs(
            run(h200, few, neutrals[:3], RADII_CM["large"])
            - run(h200, few, neutrals[:3], RADII_CM["large"], dense=True)
        ).max()
        * CM_TO_MM
    )

    # Table 4: reconstruction from the neutral
    table4, per_vertex = {}, None
    for n in HANDLE_COUNTS:
        table4[str(n)] = {}
        for name, radius in RADII_CM.items():
            out = run(placed[n], targets, neutrals, radius)
            err = _error_mm(out, targets)
            table4[str(n)][name] = float(err.mean())
            if n == 200 and name == "medium":
                per_vertex, medium_out = err, out

    baseline = _interpolation_baseline(h200, targets, neutral, RADII_CM["medium"])
    euclidean = _error_mm(run(euclidean_h200, targets, neutrals, RADII_CM["medium"]), targets)

    # Figure 15: shape-preserving layers, each re-targeting the remaining error
    layers, current = [], neutrals
    for _ in range(3):
        current = run(h200, targets, current, RADII_CM["medium"])
        layers.append(float(_error_mm(current, targets).mean()))

    # forward pass, warm jit (one pose, 200 handles)
    displacement = targets[0, h200.index] - neutral[h200.index]
    neural(h200, displacement, RADII_CM["medium"], FALLOFF_PER_CM).block_until_ready()
    times = []
    for _ in range(10 if args.quick else 30):
        start = time.perf_counter()
        neural(h200, displacement, RADII_CM["medium"], FALLOFF_PER_CM).block_until_ready()
        times.append(time.perf_counter() - start)

    neutral_error = _error_mm(neutrals, targets)
    n_capture = len(capture_test)
    results = {
        "zero_preservation_max_mm": zero_max,
        "outside_region_change_max_mm": outside_max,
        "handles_radius_mm": table4,
        "layers_mm": layers,
        "forward_ms": float(np.median(times) * 1e3),
        "train_minutes": state["seconds"] / 60.0,
        "parameters": parameter_count(model),
        "train_steps": state["step"],
        "variant": state["options"]["variant"],
        "held_out_poses": {"capture_frames": n_capture, "random_poses": len(poses) - n_capture},
        "neutral_vs_target_mean_mm": float(neutral_error.mean()),
        "heldout_200_medium_capture_mm": float(per_vertex[:n_capture].mean()),
        "heldout_200_medium_random_mm": float(per_vertex[n_capture:].mean()),
        "heldout_200_medium_p95_mm": float(np.percentile(per_vertex, 95)),
        "interpolation_baseline_200_medium_mm": float(baseline.mean()),
        "interpolation_baseline_200_medium_capture_mm": float(baseline[:n_capture].mean()),
        "interpolation_baseline_200_medium_random_mm": float(baseline[n_capture:].mean()),
        "handle_placement": "farthest-point from vertex 0, geodesic",
        "euclidean_placement_200_medium_mm": {
            "all": float(euclidean.mean()),
            "capture": float(euclidean[:n_capture].mean()),
            "random": float(euclidean[n_capture:].mean()),
        },
        "radii_cm": RADII_CM,
        "falloff_per_cm": FALLOFF_PER_CM,
        "outside_region_vertices_max": outside_count,
        "blocked_vs_dense_max_mm": blocked_vs_dense,
    }
    results["provenance"] = provenance(experiment_command(__file__, argv))
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)

    rows = [f"| handles | {' | '.join(f'{k} ({v:g} cm)' for k, v in RADII_CM.items())} |"]
    rows.append("|---" * (len(RADII_CM) + 1) + "|")
    for n, by_radius in table4.items():
        rows.append(f"| {n} | " + " | ".join(f"{by_radius[k]:.3f}" for k in RADII_CM) + " |")
    table = (
        f"Held-out mean per-vertex error (mm), reconstruction from the neutral, geodesic "
        f"farthest-point handles, falloff "
        f"{FALLOFF_PER_CM:g}/cm, {n_capture} capture frames + {len(poses) - n_capture} random "
        f"poses (the neutral itself is {results['neutral_vs_target_mean_mm']:.3f} mm away)\n\n"
        + "\n".join(rows)
        + "\n\n| quantity | value |\n|---|---|\n"
        + "".join(
            f"| {k} | {v} |\n"
            for k, v in (
                ("zero_preservation_max_mm", f"{zero_max:g}"),
                ("outside_region_change_max_mm", f"{outside_max:g}"),
                ("layers_mm (1, 2, 3)", " / ".join(f"{x:.3f}" for x in layers)),
                ("forward_ms (9,409 vertices, 200 handles, warm)", f"{results['forward_ms']:.1f}"),
                ("train_minutes / steps", f"{results['train_minutes']:.1f} / {state['step']}"),
                ("parameters", results["parameters"]),
                (
                    "no network (mask-weighted mean of handle displacements), 200 medium: "
                    "all / capture / random (mm)",
                    f"{results['interpolation_baseline_200_medium_mm']:.3f} / "
                    f"{results['interpolation_baseline_200_medium_capture_mm']:.3f} / "
                    f"{results['interpolation_baseline_200_medium_random_mm']:.3f}",
                ),
                (
                    "200 handles medium, Euclidean farthest-point placement instead: "
                    "all / capture / random (mm)",
                    " / ".join(
                        f"{v:.3f}" for v in results["euclidean_placement_200_medium_mm"].values()
                    ),
                ),
                (
                    "200 handles medium: capture / random / p95 (mm)",
                    f"{results['heldout_200_medium_capture_mm']:.3f} / "
                    f"{results['heldout_200_medium_random_mm']:.3f} / "
                    f"{results['heldout_200_medium_p95_mm']:.3f}",
                ),
            )
        )
    )
    save_text(args.out / "table.md", table)
    _figure_mask(neural, neutral, faces, targets, args.out / "mask_radii.png")
    _figure_error(per_vertex, medium_out, targets, faces, args.out / "heldout_error.png")
    print(table)
    print(f"wrote {args.out}/results.json, table.md, mask_radii.png, heldout_error.png")
    return results


def _figure_mask(neural, neutral, faces, targets, path):
    """One handle beside the left mouth corner, two radii: influence in colour on the
    deformed result (the paper's Figure 4)."""
    corner = int(
        np.argmax(neutral[:, 0] * (np.abs(neutral[:, 1] + 3.3) < 0.4) * (neutral[:, 2] > 9))
    )
    handles = neural.handles(np.array([corner]))
    lift = np.array([[0.3, 0.6, 0.0]], np.float32)
    fig, axes = plt.subplots(1, 2, figsize=(7, 4.2))
    for ax, radius in zip(axes, (1.0, 3.0), strict=True):
        shape = np.asarray(neural(handles, lift, radius, FALLOFF_PER_CM))
        mask = np.asarray(influence_mask(handles.distance, [radius], [FALLOFF_PER_CM], CLAMP))[:, 0]
        mapper = plot_vertex_scalar(
            ax,
            shape,
            faces,
            mask,
            vmin=0.0,
            vmax=1.0,
            cmap="viridis",
            title=f"radius {radius:g} cm",
        )
    fig.suptitle("one handle beside the left mouth corner, moved 6.7 mm (falloff 3/cm)")
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="influence mask")
    save_figure(fig, path)


def _figure_error(per_vertex, out, targets, faces, path):
    worst = int(np.argmax(per_vertex.mean(axis=1)))
    fig, axes = plt.subplots(1, 2, figsize=(7, 4.2))
    mapper = plot_vertex_scalar(
        axes[0],
        targets[0],
        faces,
        per_vertex.mean(axis=0),
        vmax=10.0,
        title=f"mean over {len(targets)} held-out poses\n200 handles, medium radius",
    )
    plot_vertex_scalar(
        axes[1],
        out[worst],
        faces,
        per_vertex[worst],
        vmax=10.0,
        title=f"worst pose ({worst}): mean {per_vertex[worst].mean():.2f} mm",
    )
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="per-vertex error (mm)")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
