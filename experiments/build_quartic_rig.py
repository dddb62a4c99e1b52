"""Build the standard ict-quartic rig and measure it against the nonlinear blend.

    python experiments/build_quartic_rig.py --out experiments/results/build_quartic_rig

Writes results.json (the keys of issue 2), table.md and PNG figures to --out.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM, distance_percentile_mm, per_vertex_distance
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.data import load_livelinkface
from canrig_jax.mesh import DeformationGradientBlend
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import evaluate_batch, ict_quartic_rig, random_sparse_poses
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="cached rig, 30 frames, 20 poses")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    start = time.perf_counter()
    rig, report = ict_quartic_rig(args.data_dir, rebuild=not args.quick)
    build_seconds = report.seconds if args.quick else time.perf_counter() - start
    names, faces = rig.names, np.asarray(rig.faces)
    blend = DeformationGradientBlend(rig.neutral, rig.deltas, faces)

    capture = load_livelinkface(args.data_dir).weights_for(names, missing="zero")
    n_random = 20 if args.quick else 200
    poses = np.concatenate(
        [
            capture[:30] if args.quick else capture,
            random_sparse_poses(np.random.default_rng(args.seed), n_random, names),
        ]
    )
    nonlinear = blend(poses)
    quartic = np.asarray(evaluate_batch(rig, poses))
    linear = np.asarray(evaluate_batch(rig.linear(), poses))

    results = {
        "n_vertices": rig.n_vertices,
        "n_blendshapes": rig.n_blendshapes,
        "n_pairs": rig.n_correctives(2),
        "n_triplets": rig.n_correctives(3),
        "n_quads": rig.n_correctives(4),
        "corner_max_error_mm": report.corner_max_error * CM_TO_MM,
        "linear_vs_nonlinear_p95_mm": distance_percentile_mm(linear, nonlinear),
        "quartic_vs_nonlinear_p95_mm": distance_percentile_mm(quartic, nonlinear),
        "degenerate_triangles": blend.fallback_counts.total,
        "build_seconds": build_seconds,
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)

    linear_err = per_vertex_distance(linear, nonlinear) * CM_TO_MM
    quartic_err = per_vertex_distance(quartic, nonlinear) * CM_TO_MM
    n_capture = len(poses) - n_random
    fallback = blend.fallback_counts
    rows = [
        ("vertices / blendshapes", f"{rig.n_vertices} / {rig.n_blendshapes}"),
        (
            "correctives: pairs / triplets / quads",
            "{} / {} / {}".format(*(rig.n_correctives(n) for n in (2, 3, 4))),
        ),
        (
            "candidates examined: pairs / triplets / quads",
            "{} / {} / {}".format(*(report.candidates.get(n, 0) for n in (2, 3, 4))),
        ),
        (
            "largest corrective (mm): pairs / triplets / quads",
            "{:.2f} / {:.2f} / {:.2f}".format(
                *(report.max_magnitude.get(n, 0.0) * CM_TO_MM for n in (2, 3, 4))
            ),
        ),
        ("max error at selected corners (mm)", f"{results['corner_max_error_mm']:.2e}"),
        (
            "fallback triangles (degenerate / inverted / near 180 deg)",
            f"{fallback.total} ({fallback.degenerate} / {fallback.inverted} / "
            f"{fallback.near_half_turn})",
        ),
        (
            "pose set",
            f"{n_capture} Live Link frames + {n_random} random sparse poses (4-10 active)",
        ),
        (
            "linear vs nonlinear: mean / p95 / max (mm)",
            f"{linear_err.mean():.3f} / {np.percentile(linear_err, 95):.3f} / "
            f"{linear_err.max():.2f}",
        ),
        (
            "quartic vs nonlinear: mean / p95 / max (mm)",
            f"{quartic_err.mean():.3f} / {np.percentile(quartic_err, 95):.3f} / "
            f"{quartic_err.max():.2f}",
        ),
        (
            "  on Live Link frames only, p95 linear / quartic (mm)",
            f"{np.percentile(linear_err[:n_capture], 95):.3f} / "
            f"{np.percentile(quartic_err[:n_capture], 95):.3f}",
        ),
        (
            "  on random poses only, p95 linear / quartic (mm)",
            f"{np.percentile(linear_err[n_capture:], 95):.3f} / "
            f"{np.percentile(quartic_err[n_capture:], 95):.3f}",
        ),
        ("build seconds", f"{build_seconds:.1f}"),
    ]
    table = "| quantity | value |\n|---|---|\n" + "".join(f"| {k} | {v} |\n" for k, v in rows)
    save_text(args.out / "table.md", table)

    _plot_largest_correctives(rig, args.out / "largest_correctives.png")
    worst = int(np.argmax(linear_err.max(axis=1)))
    fig, axes = plt.subplots(1, 2, figsize=(7, 4.2))
    for ax, err, label in zip(axes, (linear_err, quartic_err), ("linear", "quartic"), strict=True):
        mapper = plot_vertex_scalar(
            ax,
            nonlinear[worst],
            faces,
            err[worst],
            vmax=5.0,
            title=f"{label} rig vs nonlinear blend\npose {worst}, max {err[worst].max():.2f} mm",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="per-vertex distance (mm)")
    save_figure(fig, args.out / "worst_pose_error.png")
    print(table)
    print(f"wrote {args.out}/results.json, table.md, largest_correctives.png, worst_pose_error.png")
    return results


def _plot_largest_correctives(rig, path: Path, per_order=(4, 2, 2)):
    panels = []
    for order, count in zip((2, 3, 4), per_order, strict=True):
        table = rig.corrective(order)
        if table is None:
            continue
        magnitude = np.linalg.norm(np.asarray(table.deltas), axis=2) * CM_TO_MM
        for row in np.argsort(-magnitude.max(axis=1))[:count]:
            per_vertex = np.zeros(rig.n_vertices)
            per_vertex[np.asarray(table.vertices)] = magnitude[row]
            label = "\n+ ".join(rig.names[i] for i in np.asarray(table.indices[row]))
            panels.append((per_vertex, label))
    cols = 4
    fig, axes = plt.subplots((len(panels) + cols - 1) // cols, cols, figsize=(3 * cols, 8.5))
    for ax in axes.ravel()[len(panels) :]:
        ax.axis("off")
    for ax, (values, label) in zip(axes.ravel(), panels, strict=False):
        mapper = plot_vertex_scalar(
            ax,
            rig.neutral,
            rig.faces,
            values,
            vmax=5.0,
            title=f"{label}\nmax {values.max():.2f} mm",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.6, label="corrective magnitude (mm)")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
