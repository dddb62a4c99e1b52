"""Mesh learning foundations on real heads: operators, diffusion checks, deformation transfer.

    python experiments/mesh_foundations.py --out experiments/results/mesh_foundations

Writes results.json (the keys of issue 6), table.md and PNG figures to --out.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig._diffusion import LearnedDiffusion
from canrig_jax.data import ict_identity, load_ict, load_mediapipe_face
from canrig_jax.mesh import MeshOperators, closest_point_correspondence, decimate, flip_quad_split
from canrig_jax.mesh._operators import mesh_geometry
from canrig_jax.mesh._transfer import identity_correspondence
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import BlendshapeRig, deformation_transfer
from canrig_jax.watchdog import run_watched


def smooth_field(vertices: np.ndarray) -> np.ndarray:
    """Two smooth functions of position (cm), (V, 2)."""
    x, y, z = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    return np.stack([np.sin(x / 2.0) + 0.3 * z, np.cos(y / 3.0) * (1 + 0.1 * x)], axis=1)


def diffuse(geometry, method: str, time_cm2: float) -> np.ndarray:
    layer = LearnedDiffusion(2, method, init_time=time_cm2)
    features = jnp.asarray(smooth_field(geometry.vertices), jnp.float32)
    return np.asarray(eqx.filter_jit(layer)(features, MeshOperators.from_geometry(geometry)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="k=64, 2 identities, 2,000 vertices")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--k", type=int, default=128, help="eigenpairs")
    parser.add_argument("--identities", type=int, default=10)
    parser.add_argument("--target-vertices", type=int, default=5000)
    command_args = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(command_args)
    k = 64 if args.quick else args.k  # more than ICT's 56 components
    n_identities = 2 if args.quick else args.identities
    target_vertices = 2000 if args.quick else args.target_vertices
    time_cm2 = 1.0
    results: dict = {"k": k, "diffusion_time_cm2": time_cm2}

    head = load_ict(args.data_dir)
    with tempfile.TemporaryDirectory() as cache:
        # -- operators on the whole head, first call and cached call --------------------------
        start = time.perf_counter()
        geometry = mesh_geometry(head.neutral, head.faces, k=k, cache=cache)
        first = time.perf_counter() - start
        start = time.perf_counter()
        cached = mesh_geometry(head.neutral, head.faces, k=k, cache=cache)
        second = time.perf_counter() - start
        assert cached.from_cache
        nonzero = geometry.eigenvalues[geometry.eigenvalues > 0]
        results["operator_seconds"] = {"first": first, "cached": second}
        results["load_average_1min"] = os.getloadavg()[0]  # shared CPU: timings depend on it
        results["n_vertices"] = geometry.n_vertices
        results["n_components"] = geometry.n_components
        results["n_zero_eigenvalues"] = geometry.n_zero_eigenvalues
        results["zero_eigenvalue_rule"] = "lambda * total_area < 1e-6"
        results["smallest_nonzero_eigenvalue_times_area"] = (
            float(nonzero.min() * geometry.total_area) if nonzero.size else None
        )
        results["isolated_vertices"] = int(geometry.isolated_vertices.size)
        results["degenerate_faces"] = geometry.n_degenerate_faces

        # -- spectral (full basis) vs expm, implicit vs sparse solve, on MediaPipe ------------
        mediapipe = load_mediapipe_face(args.data_dir)
        small = mesh_geometry(mediapipe.neutral, mediapipe.faces, k=468, cache=cache)
        u = smooth_field(small.vertices)
        operator = -(sp.diags(1.0 / small.mass) @ small.laplacian)
        spectral_errors, implicit_errors = [], []
        for t in (0.1, 1.0, 10.0):
            expm = np.stack([spla.expm_multiply(t * operator, u[:, c]) for c in range(2)], 1)
            spectral = diffuse(small, "spectral", t)
            spectral_errors.append(np.abs(spectral - expm).max() / np.abs(expm).max())
            system = (sp.diags(small.mass) + t * small.laplacian).tocsc()
            solved = np.stack([spla.spsolve(system, small.mass * u[:, c]) for c in range(2)], 1)
            implicit = diffuse(small, "implicit", t)
            implicit_errors.append(np.abs(implicit - solved).max() / np.abs(solved).max())
        results["spectral_vs_expm_max_error"] = float(max(spectral_errors))
        results["implicit_vs_spsolve_max_error"] = float(max(implicit_errors))
        results["diffusion_check_mesh"] = "MediaPipe canonical face, 468 vertices, full basis"

        # -- retriangulation agreement on the whole head ---------------------------------------
        remeshings = {
            "flip_quad_split": flip_quad_split(head.neutral, head.faces),
            f"decimate_{target_vertices}": decimate(head.neutral, head.faces, target_vertices),
        }
        agreement = {}
        difference_maps = {}
        source_part = np.searchsorted(
            head.part_vertex_range[:, 1], np.arange(head.n_vertices), side="right"
        )
        skin_parts = [head.part_names.index(p) for p in ("Face", "Head and Neck")]
        for method in ("spectral", "implicit"):
            reference = diffuse(geometry, method, time_cm2)
            scale = np.ptp(reference, axis=0)
            for name, remeshed in remeshings.items():
                other_geometry = mesh_geometry(remeshed.vertices, remeshed.faces, k=k, cache=cache)
                other = diffuse(other_geometry, method, time_cm2)
                difference = np.abs(other - remeshed.map.carry(reference)) / scale
                skin = np.isin(source_part[head.faces[remeshed.map.triangle, 0]], skin_parts)
                agreement[f"{method}/{name}"] = {
                    "max": float(difference.max()),
                    "mean": float(difference.mean()),
                    "q99": float(np.percentile(difference.max(axis=1), 99)),
                    "skin_max": float(difference[skin].max()),
                    "skin_mean": float(difference[skin].mean()),
                }
                difference_maps[(method, name)] = (remeshed, difference.max(axis=1))
        headline = agreement["spectral/flip_quad_split"]
        results["retriangulation_agreement"] = {
            "max": headline["max"],
            "mean": headline["mean"],
            "relative_to": "range of the diffused field; spectral, ICT quad split vs flipped",
            "all": agreement,
        }

    # -- deformation transfer: generic head -> decimated identities -------------------------------
    rig = BlendshapeRig(head.neutral, head.deltas, (), head.names, head.faces)
    rng = np.random.default_rng(args.seed)
    errors, copy_errors, same_topology_errors, seconds = [], [], [], []
    example = None
    for i in range(n_identities):
        target = ict_identity(rng.standard_normal(100), args.data_dir, model=head)
        # same topology (identity correspondence), a reference
        same = deformation_transfer(rig, target, identity_correspondence(head.faces, len(target)))
        same_topology_errors.append(
            np.linalg.norm(np.asarray(same.deltas) - head.deltas, axis=-1).ravel() * CM_TO_MM
        )
        start = time.perf_counter()
        remeshed = decimate(target, head.faces, target_vertices)
        landmarks = remeshed.nearest_vertices(target[head.landmarks])
        correspondence = closest_point_correspondence(
            head.neutral, head.faces, remeshed.vertices, remeshed.faces, head.landmarks, landmarks
        )
        transferred = deformation_transfer(rig, remeshed.vertices, correspondence)
        seconds.append(time.perf_counter() - start)
        truth = remeshed.map.carry(head.deltas)
        error = np.linalg.norm(np.asarray(transferred.deltas) - truth, axis=-1) * CM_TO_MM
        errors.append(error.ravel())
        copied = correspondence.vertex_map.carry(head.deltas)
        copy_errors.append(np.linalg.norm(copied - truth, axis=-1).ravel() * CM_TO_MM)
        if example is None:
            example = (remeshed, transferred, truth, error)
        print(f"identity {i}: {remeshed.n_vertices} vertices, DT mae {error.mean():.3f} mm")
    errors = np.concatenate(errors)
    copy_errors = np.concatenate(copy_errors)
    same_topology_errors = np.concatenate(same_topology_errors)
    magnitude = np.linalg.norm(head.deltas, axis=-1) * CM_TO_MM
    results["deformation_transfer_mae_mm"] = float(errors.mean())
    results["deformation_transfer_q95_mm"] = float(np.percentile(errors, 95))
    results["deformation_transfer"] = {
        "identities": n_identities,
        "target_vertices": int(example[0].n_vertices),
        "expressions": int(head.deltas.shape[0]),
        "max_mm": float(errors.max()),
        "seconds_per_identity": float(np.mean(seconds)),
        "same_topology_mae_mm": float(same_topology_errors.mean()),
        "same_topology_q95_mm": float(np.percentile(same_topology_errors, 95)),
        "delta_copy_through_correspondence_mae_mm": float(copy_errors.mean()),
        "delta_copy_through_correspondence_q95_mm": float(np.percentile(copy_errors, 95)),
        "expression_magnitude_mean_mm": float(magnitude.mean()),
        "expression_magnitude_q95_mm": float(np.percentile(magnitude, 95)),
    }

    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, command_args)
    save_json(args.out / "results.json", {**results, "provenance": provenance(command)})
    record_command(args.out, command)
    table = _table(results)
    save_text(args.out / "table.md", table)
    _plot_transfer(example, head.names, args.out / "deformation_transfer_error.png")
    _plot_agreement(difference_maps, args.out / "retriangulation_difference.png")
    print(table)
    print(f"wrote {args.out}/results.json, table.md, COMMAND and PNG figures")
    return results


def _table(r: dict) -> str:
    dt = r["deformation_transfer"]
    rows = [
        ("ICT head vertices / components", f"{r['n_vertices']} / {r['n_components']}"),
        (
            "operators (k = {}): first call / cached call (s)".format(r["k"]),
            f"{r['operator_seconds']['first']:.1f} / {r['operator_seconds']['cached']:.3f} "
            f"(load average {r['load_average_1min']:.1f} on this machine)",
        ),
        (
            "zero eigenvalues (rule: {})".format(r["zero_eigenvalue_rule"]),
            f"{r['n_zero_eigenvalues']} (first non-zero: lambda * area = "
            f"{r['smallest_nonzero_eigenvalue_times_area']:.1f})",
        ),
        (
            "spectral (full basis) vs expm_multiply, max rel. error",
            f"{r['spectral_vs_expm_max_error']:.1e}",
        ),
        ("implicit (CG) vs spsolve, max rel. error", f"{r['implicit_vs_spsolve_max_error']:.1e}"),
    ]
    for key, value in r["retriangulation_agreement"]["all"].items():
        rows.append(
            (
                f"retriangulation {key}, t = {r['diffusion_time_cm2']} cm^2: max / mean / q99",
                f"{100 * value['max']:.2f} % / {100 * value['mean']:.3f} % / "
                f"{100 * value['q99']:.2f} % of range "
                f"(skin only: {100 * value['skin_max']:.2f} % / {100 * value['skin_mean']:.3f} %)",
            )
        )
    rows += [
        (
            f"DT generic -> {dt['identities']} identities (~{dt['target_vertices']} vertices): "
            "MAE / q95 (mm)",
            f"{r['deformation_transfer_mae_mm']:.3f} / {r['deformation_transfer_q95_mm']:.3f}",
        ),
        ("  DT max (mm)", f"{dt['max_mm']:.2f}"),
        (
            "  DT on the same topology (identity correspondence): MAE / q95 (mm)",
            f"{dt['same_topology_mae_mm']:.3f} / {dt['same_topology_q95_mm']:.3f}",
        ),
        (
            "  copying deltas through the correspondence: MAE / q95 (mm)",
            f"{dt['delta_copy_through_correspondence_mae_mm']:.3f} / "
            f"{dt['delta_copy_through_correspondence_q95_mm']:.3f}",
        ),
        (
            "  expression magnitude: mean / q95 (mm)",
            f"{dt['expression_magnitude_mean_mm']:.3f} / {dt['expression_magnitude_q95_mm']:.3f}",
        ),
        (
            "  seconds per identity (decimate + correspondence + DT)",
            f"{dt['seconds_per_identity']:.1f}",
        ),
    ]
    return "| quantity | value |\n|---|---|\n" + "".join(f"| {a} | {b} |\n" for a, b in rows)


def _plot_transfer(example, names, path: Path) -> None:
    remeshed, transferred, truth, error = example
    jaw = names.index("jawOpen") if "jawOpen" in names else 0
    order = [int(i) for i in np.argsort(-error.max(axis=1)) if i != jaw]
    worst = order[0]
    fig, axes = plt.subplots(1, 4, figsize=(13, 4.2))
    for column, index in enumerate((jaw, worst)):
        posed_truth = remeshed.vertices + truth[index]
        posed = remeshed.vertices + np.asarray(transferred.deltas[index], np.float64)
        plot_vertex_scalar(
            axes[2 * column],
            posed_truth,
            remeshed.faces,
            np.linalg.norm(truth[index], axis=1) * CM_TO_MM,
            vmax=10.0,
            cmap="viridis",
            title=f"{names[index]}: ground truth\n(displacement, 0-10 mm)",
        )
        mapper = plot_vertex_scalar(
            axes[2 * column + 1],
            posed,
            remeshed.faces,
            error[index],
            vmax=10.0,
            title=f"{names[index]}: DT error\nmean {error[index].mean():.2f} mm, "
            f"max {error[index].max():.1f} mm",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="error (mm)")
    save_figure(fig, path)


def _plot_agreement(maps: dict, path: Path) -> None:
    keys = [key for key in maps if key[0] == "spectral"]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 4.2))
    for ax, key in zip(np.atleast_1d(axes), keys, strict=True):
        remeshed, difference = maps[key]
        mapper = plot_vertex_scalar(
            ax,
            remeshed.vertices,
            remeshed.faces,
            100 * difference,
            vmax=2.0,
            title=f"{key[0]} diffusion, {key[1]}\nmax {100 * difference.max():.2f} % of range",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="|difference| (% of field range)")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
