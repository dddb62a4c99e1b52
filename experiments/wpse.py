"""Weighted pose space editing against PSE, the fix-shape method and the ict-quartic rig.

    python experiments/wpse.py --out experiments/results/wpse
    python experiments/wpse_timing.py --out experiments/results/wpse

The linear ICT face rig driven by the Live Link capture and random sparse poses; what the
artist wants is the deformation-gradient blend. Edits are sculpted at the most problematic
frames; every other frame is held out. Writes results.json (held-out errors, widths,
locality, overshoot, layering, search, few edits, temporal smoothness, reuse), table.md and
PNG figures to --out. The timing rows (Table 1) are ``experiments/wpse_timing.py``'s, run
next on the same folder. The protocols are ``canrig_jax.wpse``'s (``compare_methods``,
``few_edit_errors``, ``temporal_smoothness``, ``reuse_by_search``, the probes).
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import per_vertex_distance
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.data import load_livelinkface
from canrig_jax.mesh import DeformationGradientBlend
from canrig_jax.papers import wpse as wpse_paper
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import evaluate_batch, ict_linear_rig, ict_quartic_rig, random_sparse_poses
from canrig_jax.watchdog import run_watched

BUDGETS = (10, 50)
FEW_EDIT_BUDGETS = (5, 10, 20, 50)
REUSE_LIBRARY_EDITS = 10
MIN_EDIT_DISTANCE = 0.5  # weight units between edited frames ("spread out")
SUPPORT_TOL_CM = 1e-4  # vertices whose edits all stay below 1 micrometre are not stored


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="100 random poses")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)

    rig = ict_linear_rig(args.data_dir)
    quartic, _ = ict_quartic_rig(args.data_dir, progress=False)
    names, faces = rig.names, np.asarray(rig.faces)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(names, missing="zero")
    n_random = 100 if args.quick else 400
    poses = np.concatenate([capture, random_sparse_poses(rng, n_random, names)])
    blend = DeformationGradientBlend(rig.neutral, rig.deltas, faces)
    desired = blend(poses).astype(np.float32)
    linear = np.asarray(evaluate_batch(rig, poses))
    frame_error = per_vertex_distance(linear, desired).mean(axis=1)
    edit_frames = wpse_paper.select_edit_frames(frame_error, poses, max(BUDGETS), MIN_EDIT_DISTANCE)
    held_out = np.setdiff1d(np.arange(len(poses)), edit_frames)
    print(f"{len(poses)} frames, {len(held_out)} held out, edits at the worst spread-out frames")
    mouth = [i for i, n in enumerate(names) if n.startswith(("mouth", "jaw"))]
    eyes = [i for i, n in enumerate(names) if n.startswith("eye")]
    frames = (poses, desired, linear)

    compared = wpse_paper.compare_methods(
        rig,
        *frames,
        edit_frames,
        held_out,
        budgets=BUDGETS,
        sculpt=blend,
        others={"quartic": np.asarray(evaluate_batch(quartic, poses[held_out]))},
        support_tol=SUPPORT_TOL_CM,
    )
    errors, models, sigma = compared.errors, compared.models, compared.sigma
    for b in BUDGETS:
        print(f"p{b}", {m: round(errors[m][f"p{b}"]["mean_mm"], 4) for m in errors})
    few_edits, new_width = wpse_paper.few_edit_errors(
        rig,
        *frames,
        edit_frames,
        held_out,
        budgets=FEW_EDIT_BUDGETS,
        known_sigma={key: record["loo_sigma"] for key, record in sigma.items()},
        support_tol=SUPPORT_TOL_CM,
    )
    for budget, row in few_edits.items():
        print("few edits", budget, {m: round(v["mean_mm"], 4) for m, v in row.items()})
    temporal, curves = wpse_paper.temporal_smoothness(
        rig,
        *frames,
        edit_frames,
        np.arange(len(capture)),
        sigma=new_width["wpse_new_width_p10"]["sigma"],
        support_tol=SUPPORT_TOL_CM,
    )
    _temporal_figure(temporal, curves, args.out)
    reuse = wpse_paper.reuse_by_search(
        rig,
        *frames,
        np.arange(len(capture)),
        region_channels=mouth,
        library_size=REUSE_LIBRARY_EDITS,
        min_distance=MIN_EDIT_DISTANCE / 2,
        support_tol=SUPPORT_TOL_CM,
    )
    print("reuse", {k: v for k, v in reuse.items() if k.startswith(("error", "tau"))})
    locality = wpse_paper.locality_probe(
        rig,
        {m: models[m, 50] for m in ("pse", "wpse")},
        poses,
        edit_frames,
        linear,
        blend,
        rng,
        eye_channels=eyes,
        mouth_channels=mouth,
    )
    overshoot, magnitude = wpse_paper.overshoot_sweep(
        rig,
        models["fsm", 50],
        {f"{m}_p50": models[m, 50] for m in ("wpse", "wpse_rest_pose")},
        blend,
        sigma=sigma["wpse_p50"]["loo_sigma"],
    )
    _overshoot_figure(overshoot, magnitude, args.out)
    layering = wpse_paper.layering_probe(
        rig, poses[edit_frames[0]], blend, sigma=sigma["wpse_p50"]["loo_sigma"]
    )
    search = _search(rig, poses, edit_frames, int(held_out[0]), linear, mouth, eyes, args.out)
    random_rows = np.flatnonzero(held_out >= len(capture))
    _error_maps(compared.maps, desired[held_out], faces, random_rows, args.out)

    results = {
        "errors": errors,
        "locality": locality,
        "overshoot": overshoot,
        "layering": layering,
        "search": search,
        "sigma": sigma,
        "sigma_sweep_held_out_mean_mm": compared.sweep,
        "max_correction_at_rest_pose_mm": compared.rest_correction,
        "few_edits": few_edits,
        "new_width": new_width,
        "temporal": temporal,
        "reuse": reuse,
        "protocol": {
            "frames": len(poses),
            "capture_frames": len(capture),
            "random_poses": n_random,
            "edit_frames": edit_frames.tolist(),
            "held_out_frames": len(held_out),
            "min_edit_distance": MIN_EDIT_DISTANCE,
            "support_tol_cm": SUPPORT_TOL_CM,
            "quick": args.quick,
        },
    }
    results["provenance"] = provenance(experiment_command(__file__, argv))
    save_json(args.out / "results.json", results)
    table = wpse_paper.results_table(results)
    save_text(args.out / "table.md", table)
    print(table)
    print(f"wrote {args.out}/results.json, table.md and PNG figures")
    print(f"timing rows: python experiments/wpse_timing.py --out {args.out}")
    return results


def _temporal_figure(temporal, curves, out_dir, around=40):
    """Figure 6 analog: the correction of one edit over the take around the edited frame."""
    frame, n = temporal["edited_frame"], temporal["frames"]
    take = np.arange(n)
    lo, hi = max(frame - around, 0), min(frame + around + 1, n)
    fig, ax = plt.subplots(figsize=(6.0, 3.4))
    ax.plot(take[lo:hi], curves["size"][lo:hi], label="max correction (mm)", lw=1.8)
    ax.plot(take[lo + 1 : hi], curves["step"][lo : hi - 1], label="correction step (mm/frame)")
    ax.plot(
        take[lo + 1 : hi],
        curves["take_step"][lo : hi - 1],
        label="take's own step (mm/frame)",
        color="grey",
        ls="--",
        lw=1,
    )
    ax.axvline(frame, color="red", lw=0.8, ls=":", label=f"edited frame {frame}")
    ax.set_xlabel("Live Link frame")
    ax.set_ylabel("mm")
    ax.set_title(
        f"One edit applied over the take (WPSE, sigma {temporal['sigma']:.3f}; Seol et al. Fig. 6)",
        fontsize=9,
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out_dir / "temporal.png")


def _overshoot_figure(overshoot, magnitude, out_dir):
    """Figure 9 analog: the largest correction along the sweep of the pair."""
    t = np.linspace(0.0, 1.5, 31)  # wpse_paper.overshoot_sweep's default sweep
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for k, v in magnitude.items():
        ax.plot(t, v, label=k, lw=2 if k == "desired" else 1.5)
    ax.axvline(1.0, color="grey", lw=0.8, ls=":")
    first, second = overshoot["pair"]
    ax.set_xlabel(f"w[{first}] = w[{second}]")
    ax.set_ylabel("max correction over vertices (mm)")
    ax.set_title("Overshoot past the sculpted corner (Seol et al. Fig. 9)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out_dir / "overshoot.png")


def _search(rig, poses, edit_frames, query_frame, linear, mouth, eyes, out_dir, top=3):
    """Section 4: the edit library ranked by the mouth ROI and by the eye ROI for one query
    frame; the result rows and the figure (the query and the first ``top`` found)."""
    regions = {"mouth": mouth, "eyes": eyes}
    found = wpse_paper.search_by_region(rig, poses[edit_frames], poses[query_frame], regions)
    result = {"query_frame": query_frame}
    fig, axes = plt.subplots(2, top + 1, figsize=(3 * (top + 1), 6.4))
    for row, (region_name, region) in enumerate(found.items()):
        roi, hits = region["roi"], region["found"]
        result[region_name] = {
            "roi_vertices": int(roi.size),
            "tau": region["tau"],
            "candidates": [
                {"edit_frame": int(edit_frames[i]), "energy": float(e)}
                for i, e in zip(hits.indices, hits.energies, strict=True)
            ],
        }
        highlight = np.zeros(rig.n_vertices)
        highlight[roi] = 4.0
        plot_vertex_scalar(
            axes[row, 0],
            linear[query_frame],
            rig.faces,
            highlight,
            title=f"query frame {query_frame}\n{region_name} ROI ({roi.size} vertices)",
        )
        for col in range(top):
            ax = axes[row, col + 1]
            if col >= hits.indices.size:
                ax.axis("off")
                continue
            frame = int(edit_frames[hits.indices[col]])
            plot_vertex_scalar(
                ax,
                linear[frame],
                rig.faces,
                highlight,
                title=f"#{col + 1}: edit frame {frame}\nE = {hits.energies[col]:.2f}",
            )
    fig.suptitle("Search of sculpted edits by region of interest (ROI in orange)", fontsize=10)
    save_figure(fig, out_dir / "search.png")
    return result


def _error_maps(maps, desired, faces, random_rows, out_dir):
    """Per-vertex error (0-5 mm): mean over held-out frames, and the held-out random pose
    where the linear rig is worst (capture frames next to an edited frame are trivial)."""
    worst = int(random_rows[np.argmax(maps["linear"][random_rows].mean(axis=1))])
    methods = ("linear", "pse", "wpse", "wpse_rest_pose", "fsm", "quartic")
    fig, axes = plt.subplots(2, len(methods), figsize=(3.1 * len(methods), 8.4))
    for col, method in enumerate(methods):
        mean = maps[method].mean(axis=0)
        plot_vertex_scalar(
            axes[0, col],
            desired[worst],
            faces,
            mean,
            vmax=5.0,
            title=f"{method} (50 edits)\nheld-out mean, max {mean.max():.2f} mm",
        )
        err = maps[method][worst]
        mapper = plot_vertex_scalar(
            axes[1, col],
            desired[worst],
            faces,
            err,
            vmax=5.0,
            title=f"random pose {worst}\nmean {err.mean():.2f}, max {err.max():.2f} mm",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.6, label="distance to the nonlinear blend (mm)")
    save_figure(fig, out_dir / "error_maps.png")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
