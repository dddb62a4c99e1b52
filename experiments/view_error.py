"""An experiment's error as vertex colour: ``error.glb`` beside its PNGs, for ``canrig view``.

Recomputes one representative take of a standard experiment with its own library calls and
committed settings (not the whole experiment), and writes it with
``canrig_jax.viewer.export_error_glb``: the method's mesh at every frame (one morph target per
frame, keyed in turn) coloured by each vertex's mean error over the take, white at 0 and red
at the 95th percentile (over the scored vertices) and above:

    python experiments/view_error.py inverse_rig
    python experiments/view_error.py wpse
    python experiments/view_error.py canrig_workflows
    canrig view experiments/results/inverse_rig/error.glb

Each shows ``--frames`` (30) evenly spaced frames of its take:

- ``inverse_rig``: the ict-quartic rig inverted by converged QuarticCD at the standard run's
  chosen alpha, on frames of the Live Link take with the protocol's noise (variance 0.03 cm^2,
  a fresh draw from ``--seed``); error = solved mesh to the clean target.
- ``wpse``: WPSE with the 50 edits and the leave-one-out width of the standard run (read from
  its results.json), on its held-out frames (capture and random poses, as its held-out mean;
  keyed 0.25 s apart); error = the edited linear rig to the deformation-gradient blend (what
  the artist wants).
- ``canrig_workflows``: dialogue replacement (direct) with the committed CANRig checkpoint,
  capture frames 90-134 given the mouth of frames 135-179, as the standard run; error = the
  output to the intended shape (the target inside the mouth mask, the source elsewhere),
  scored in the mouth mask.

Writes to --out (default experiments/results/EXPERIMENT): error.glb (not committed: 3-5 MB,
rebuilt in a minute or two), error_legend.png (the colour scale), error.png (a headless
screenshot at the worst vertex's worst frame, when Chromium is installed) and error_glb.json
(the numbers and settings), and appends the command to COMMAND.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax import inverse, wpse
from canrig_jax._io import save_json
from canrig_jax._metrics import CM_TO_MM, per_vertex_distance
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.canrig import (
    NeuralRig,
    dialogue_replacement,
    expression_region,
    influence_reach,
    interior_vertices,
    load_model,
)
from canrig_jax.canrig._data import evaluate_poses
from canrig_jax.data import load_livelinkface
from canrig_jax.inverse import summarize
from canrig_jax.mesh import DeformationGradientBlend, farthest_point_vertices
from canrig_jax.rig import (
    UNIT_IN_CM,
    evaluate_batch,
    ict_linear_rig,
    ict_quartic_rig,
    random_sparse_poses,
)
from canrig_jax.viewer import export_error_glb, find_chromium, save_error_legend, screenshot_glb
from canrig_jax.watchdog import run_watched

RESULTS = Path(__file__).resolve().parent / "results"
WPSE_EDITS = 50
WPSE_SECONDS_PER_POSE = 0.25  # held-out poses are not one take: keyed 0.25 s apart


def _spread(n: int, count: int) -> np.ndarray:
    """``count`` evenly spaced indices of ``range(n)`` (all of them when n <= count)."""
    return np.unique(np.linspace(0, n - 1, min(n, count)).round().astype(int))


def _capture(data_dir, names):
    capture = load_livelinkface(data_dir)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        weights = capture.weights_for(names, missing="zero")
    frames = np.asarray(capture.frame_number, float)
    return weights, (frames - frames[0]) / float(capture.fps)


def inverse_rig_take(args) -> dict:
    """Converged QuarticCD on the noisy Live Link take (ict-quartic rig)."""
    from inverse_rig import NOISE_VARIANCE_CM2  # the experiment's protocol (a sibling script)

    standard = json.loads((RESULTS / "inverse_rig" / "results.json").read_text())
    alpha_cm2 = standard["cases"]["ict"]["quartic_cd_converged"]["alpha"]
    rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    scale = UNIT_IN_CM[rig.units]
    take, times = _capture(args.data_dir, rig.names)
    frames = _spread(len(take), args.frames)
    clean = np.asarray(evaluate_batch(rig, take[frames]))
    rng = np.random.default_rng(args.seed)
    noise = np.sqrt(NOISE_VARIANCE_CM2) / scale
    noisy = (clean + rng.normal(0, noise, clean.shape)).astype(np.float32)
    method = inverse.QuarticCD(alpha=alpha_cm2 / scale**2)
    weights = np.asarray(inverse.solve_sequence(rig, noisy, method).weights)
    solved = np.asarray(evaluate_batch(rig, weights))
    error = per_vertex_distance(solved, clean) * (UNIT_IN_CM[rig.units] * CM_TO_MM)
    row = summarize(rig, weights, clean)
    return {
        "meshes": solved,
        "faces": np.asarray(rig.faces),
        "error_mm": error,
        "times": times[frames],
        "neutral": np.asarray(rig.neutral),
        "units": rig.units,
        "region": None,
        "label": "solved mesh to clean target, mean over frames (mm)",
        "settings": {
            "rig": f"ict-quartic, {rig.n_vertices} vertices, cm",
            "method": f"QuarticCD (converged defaults), alpha {alpha_cm2} cm^2 (the standard "
            "run's choice for quartic_cd_converged)",
            "frames": frames.tolist(),
            "noise": f"variance {NOISE_VARIANCE_CM2} cm^2, seed {args.seed} (a fresh draw)",
            "error": "per-vertex distance of the solved mesh to the clean target",
        },
        "check": {
            "rmse_mean_mm_these_frames": row["rmse_mean_mm"],
            "rmse_mean_mm_standard_run_all_frames": standard["cases"]["ict"][
                "quartic_cd_converged"
            ]["rmse_mm"],
        },
    }


def wpse_take(args) -> dict:
    """WPSE (50 edits, leave-one-out width) on the standard run's held-out frames."""
    standard = json.loads((RESULTS / "wpse" / "results.json").read_text())
    protocol = standard["protocol"]
    sigma = standard["sigma"][f"wpse_p{WPSE_EDITS}"]["loo_sigma"]
    rig = ict_linear_rig(args.data_dir)
    capture, times = _capture(args.data_dir, rig.names)
    rng = np.random.default_rng(0)  # experiments/wpse.py's default seed: the same poses
    poses = np.concatenate([capture, random_sparse_poses(rng, protocol["random_poses"], rig.names)])
    if len(poses) != protocol["frames"]:
        raise ValueError(f"wpse: {len(poses)} frames, its results.json has {protocol['frames']}")
    edit_frames = np.asarray(protocol["edit_frames"])[:WPSE_EDITS]
    held_out = np.setdiff1d(np.arange(len(poses)), edit_frames)
    held_out = held_out[_spread(len(held_out), args.frames)]
    blend = DeformationGradientBlend(rig.neutral, rig.deltas, np.asarray(rig.faces))
    linear_edits = np.asarray(evaluate_batch(rig, poses[edit_frames]))
    edits = blend(poses[edit_frames]).astype(np.float32) - linear_edits
    data = wpse.prepare_edits(
        rig, poses[edit_frames], edits, support_tol=protocol["support_tol_cm"]
    )
    model = wpse.fit_prepared(data, sigma)
    linear = np.asarray(evaluate_batch(rig, poses[held_out]))
    run = jax.jit(jax.vmap(wpse.apply, (None, 0, 0)))
    edited = np.asarray(run(model, jnp.asarray(poses[held_out]), jnp.asarray(linear)))
    desired = blend(poses[held_out]).astype(np.float32)
    error = per_vertex_distance(edited, desired) * CM_TO_MM
    return {
        "meshes": edited,
        "faces": np.asarray(rig.faces),
        "error_mm": error,
        "times": np.arange(len(held_out)) * WPSE_SECONDS_PER_POSE,
        "neutral": np.asarray(rig.neutral),
        "units": rig.units,
        "region": None,
        "label": "WPSE to the sculpt, mean over frames (mm)",
        "settings": {
            "rig": f"ICT linear face, {rig.n_vertices} vertices, cm",
            "method": f"WPSE, the standard run's {WPSE_EDITS} edit frames, leave-one-out sigma "
            f"{sigma:.4g}, local frames, support_tol {protocol['support_tol_cm']} cm",
            "frames": held_out.tolist(),
            "frames_note": f"held-out frames of the standard run (capture: < {len(capture)})",
            "error": "per-vertex distance of the edited mesh to the deformation-gradient blend",
        },
        "check": {
            "wpse_mean_mm_these_frames": float(error.mean()),
            "linear_mean_mm_these_frames": float(
                (per_vertex_distance(linear, desired) * CM_TO_MM).mean()
            ),
            "wpse_mean_mm_standard_run_all_held_out": standard["errors"]["wpse"][f"p{WPSE_EDITS}"][
                "mean_mm"
            ],
        },
    }


def canrig_workflows_take(args) -> dict:
    """Dialogue replacement (direct) with the committed CANRig checkpoint."""
    # the workflow experiment's own settings
    from canrig_jax.papers.canrig.workflows import (
        DIALOGUE_HANDLES,
        DIALOGUE_RADIUS_CM,
        FALLOFF_PER_CM,
        MOUTH_THRESHOLD_CM,
    )

    standard = json.loads((RESULTS / "canrig_workflows" / "results.json").read_text())
    (s0, s1), (t0, t1) = (standard["dialogue"]["frames"][k] for k in ("source", "target"))
    quartic, _ = ict_quartic_rig(args.data_dir, progress=False)
    capture, times = _capture(args.data_dir, quartic.names)
    neutral = np.asarray(quartic.neutral, np.float32)
    model, _ = load_model(args.checkpoint, neutral)
    rig = NeuralRig(model, neutral, np.asarray(quartic.faces))
    mouth = expression_region(quartic, threshold=MOUTH_THRESHOLD_CM)
    frames = _spread(s1 + 1 - s0, args.frames)
    source = evaluate_poses(quartic, capture[s0 : s1 + 1][frames])
    target = evaluate_poses(quartic, capture[t0 : t1 + 1][frames])
    reach = float(influence_reach(DIALOGUE_RADIUS_CM, FALLOFF_PER_CM, rig.model.clamp))
    interior = interior_vertices(rig, mouth, reach)
    handles = rig.handles(interior[farthest_point_vertices(neutral[interior], DIALOGUE_HANDLES)])
    out = np.asarray(
        dialogue_replacement(
            rig, source, target, handles, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM, region=mouth
        )
    )
    intended = np.where(mouth[None, :, None], target, source)
    error = per_vertex_distance(out, intended) * CM_TO_MM
    return {
        "meshes": out,
        "faces": np.asarray(quartic.faces),
        "error_mm": error,
        "times": times[s0 : s1 + 1][frames],
        "neutral": neutral,
        "units": quartic.units,
        "region": mouth,
        "label": "dialogue output to intended, mean over frames (mm)",
        "settings": {
            "rig": f"CANRig {args.checkpoint.name} on ict-quartic, {quartic.n_vertices} vertices",
            "method": f"dialogue_replacement (direct), {DIALOGUE_HANDLES} mouth handles, radius "
            f"{DIALOGUE_RADIUS_CM} cm, falloff {FALLOFF_PER_CM}/cm",
            "frames": {"source": (s0 + frames).tolist(), "target": (t0 + frames).tolist()},
            "error": "per-vertex distance of the output to the target inside the mouth mask "
            f"({int(mouth.sum())} vertices) and to the source elsewhere; scored in the mask",
        },
        "check": {
            "mouth_difference_mm": float(error[:, mouth].mean()),
            "mouth_difference_mm_standard_run": standard["dialogue"]["mouth_difference_mm"],
            "rest_of_face_max_mm": float(error[:, ~mouth].max()),
        },
    }


EXPERIMENTS = {
    "inverse_rig": inverse_rig_take,
    "wpse": wpse_take,
    "canrig_workflows": canrig_workflows_take,
}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("experiment", choices=sorted(EXPERIMENTS))
    parser.add_argument("--out", type=Path, default=None, help="default results/EXPERIMENT")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--frames", type=int, default=30, help="evenly spaced frames shown")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=RESULTS / "canrig_workflows" / "model" / "checkpoint.eqx",
        help="canrig_workflows: the CANRig model",
    )
    args = parser.parse_args(argv)
    if args.frames < 1:
        raise ValueError(f"--frames: expected >= 1, got {args.frames}")
    out = args.out or RESULTS / args.experiment
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)

    take = EXPERIMENTS[args.experiment](args)
    glb = export_error_glb(
        out / "error.glb",
        take["meshes"],
        take["faces"],
        take["error_mm"],
        region=take["region"],
        times=take["times"] - take["times"][0],
        neutral=take["neutral"],
        units=take["units"],
    )
    save_error_legend(out / "error_legend.png", glb.vmax_mm, take["label"])
    scored = glb.vertex_error_mm if take["region"] is None else glb.vertex_error_mm[take["region"]]
    shown_at = float(glb.times[glb.worst_frame])
    screenshot = None
    if find_chromium() is not None:
        shot = screenshot_glb(glb.path, out / "error.png", time=shown_at)
        screenshot = {"file": "error.png", "time_s": shot.time, "page_errors": shot.errors}
    results = {
        "experiment": args.experiment,
        **take["settings"],
        "colour": "COLOR_0 = each vertex's mean error over the frames; white 0, red >= vmax "
        "(the 95th percentile over the scored vertices); legend: error_legend.png",
        "vmax_mm": glb.vmax_mm,
        "scored_vertices": int(scored.size),
        "mean_mm": float(scored.mean()),
        "max_mm": float(scored.max()),
        "worst_vertex": glb.worst_vertex,
        "worst_vertex_position_cm": (
            np.asarray(take["neutral"])[glb.worst_vertex] * UNIT_IN_CM[take["units"]]
        ).tolist(),
        "worst_frame": glb.worst_frame,
        "worst_frame_time_s": shown_at,
        "check": take["check"],
        "glb": {
            "file": "error.glb",
            "frames": len(glb.times),
            "bytes": glb.path.stat().st_size,
            "committed": False,
        },
        "screenshot": screenshot,
        "provenance": provenance(command),
    }
    save_json(out / "error_glb.json", results)
    record_command(
        out, command, note="error.glb (vertex colour = error) for canrig view (issue 23):"
    )
    print(
        f"{args.experiment}: mean {results['mean_mm']:.3f} mm, max {results['max_mm']:.3f} mm at "
        f"vertex {glb.worst_vertex} (frame {glb.worst_frame}); red from {glb.vmax_mm:.3f} mm; "
        f"check {take['check']}; wrote {glb.path}"
    )
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
