"""Retargeting the Live Link capture from ARKit onto the other control sets of one head:
ARKit -> SRanipal and ARKit -> FACS on the two Rocketbox heads (all 175 FBX shapes read, the
head cropped), with ``inverse.retarget``.

    python experiments/inverse_rig_retarget.py --out experiments/results/inverse_rig

The rule, fixed before measuring:

- method: ``inverse.QuarticNewton`` (its defaults: 50 iterations, tol 1e-5, box [0, 1]),
  frames solved independently (no warm start, so a frame's result does not depend on the take);
- alpha (cm^2): for each head and target set, ``inverse_rig.select_alpha`` (the largest alpha whose
  mean per-frame RMSE is within 5 % of the best) over ``ALPHAS`` on ``TRAIN_POSES`` random
  sparse poses of the source ARKit rig (``rig.random_sparse_poses``, seed 0), never on the
  capture.

Metrics on the capture (180 frames): the mesh error of a frame is the RMSE over the head crop's
vertices (mm) between the source's offsets from the neutral and the retargeted target's;
``mesh_mean_mm``, ``mesh_p95_mm`` and ``mesh_max_mm`` are its mean, 95th percentile and maximum
over frames (``vertex_max_mm``: the largest single-vertex error of the take); ``cardinality``
the mean number of target weights above ``inverse.CARDINALITY_TOL``; ``roughness``
``inverse.roughness`` of the target curves; ``ms_per_frame`` the median wall time of three
compiled ``retarget`` calls on the take (source evaluation and ``prepare`` included) over the
frames. ARKit -> ARKit (the source's own controls) is reported beside them as a floor.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax import inverse
from canrig_jax._io import update_results
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.data import data_file, load_livelinkface
from canrig_jax.inverse import CARDINALITY_TOL, roughness
from canrig_jax.papers.inverse_rig import select_alpha
from canrig_jax.render import save_figure
from canrig_jax.rig import (
    UNIT_IN_CM,
    evaluate_batch,
    load_fbx_rig,
    random_sparse_poses,
    select_control_set,
)
from canrig_jax.watchdog import run_watched

HEADS = {"rocketbox_female": "Female_Adult_01", "rocketbox_male": "Male_Adult_08"}
SETS = ("sranipal", "facs", "arkit")  # arkit: the source's own controls, a floor
ALPHAS = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3)
TRAIN_POSES = 200
TOLERANCE = 0.05


def offsets_mm(rig, weights) -> np.ndarray:
    """(T, V, 3) the rig's offsets from its neutral at ``weights``, in mm."""
    return np.asarray(evaluate_batch(rig, weights) - rig.neutral, np.float64) * (
        UNIT_IN_CM[rig.units] * CM_TO_MM
    )


def frame_rmse_mm(source_mm: np.ndarray, target_rig, weights) -> tuple[np.ndarray, np.ndarray]:
    """((T,) per-frame RMSE over vertices, (T, V) per-vertex error), mm."""
    error = np.linalg.norm(offsets_mm(target_rig, weights) - source_mm, axis=-1)
    return np.sqrt((error**2).mean(axis=1)), error


def choose_alpha(source, target, poses) -> tuple[float, list[dict]]:
    """The alpha of the rule (see the module docstring) and the sweep it was chosen from."""
    source_mm = offsets_mm(source, poses)
    sweep = []
    for alpha in ALPHAS:
        solution = inverse.retarget(source, poses, target, inverse.QuarticNewton(alpha=alpha))
        rmse, _ = frame_rmse_mm(source_mm, target, solution.weights)
        sweep.append({"alpha": alpha, "rmse_mean_mm": float(rmse.mean())})
    return float(select_alpha(sweep, TOLERANCE, method="QuarticNewton")["alpha"]), sweep


def measure(source, target, take, method) -> tuple[dict, np.ndarray]:
    """The metrics of the module docstring, and the (T,) per-frame RMSE."""
    seconds = []
    for _ in range(4):  # the first call compiles
        start = time.perf_counter()
        solution = inverse.retarget(source, take, target, method)
        weights = np.asarray(solution.weights)
        seconds.append(time.perf_counter() - start)
    if not np.all(np.isfinite(weights)):
        raise RuntimeError(f"non-finite retargeted weights onto {target.n_blendshapes} controls")
    source_mm = offsets_mm(source, take)
    rmse, error = frame_rmse_mm(source_mm, target, weights)
    motion = np.sqrt((np.linalg.norm(source_mm, axis=-1) ** 2).mean(axis=1))
    row = {
        "mesh_mean_mm": float(rmse.mean()),
        "mesh_p95_mm": float(np.percentile(rmse, 95)),
        "mesh_max_mm": float(rmse.max()),
        "vertex_max_mm": float(error.max()),
        "cardinality": float((weights > CARDINALITY_TOL).sum(axis=1).mean()),
        "roughness": roughness(weights),
        "ms_per_frame": float(np.median(seconds[1:]) / take.shape[0] * 1e3),
        "alpha": float(method.alpha),
        "n_controls": target.n_blendshapes,
        "frames": int(take.shape[0]),
        "all_finite": True,
        "converged_frames": int(np.asarray(solution.stats["converged"]).sum()),
        "source_motion_mean_mm": float(motion.mean()),
    }
    return row, rmse


def table(results: dict, command: str, n_poses: int) -> str:
    lines = [
        "## Retargeting the Live Link capture onto other control sets (Rocketbox)",
        "",
        f"ARKit curves of the capture ({next(iter(results.values()))[SETS[0]]['frames']} "
        "frames) carried onto another control set of the same "
        "head with `inverse.retarget` (QuarticNewton; alpha chosen by `select_alpha` on "
        f"{n_poses} random ARKit poses, never on the capture). Mesh error: per-frame RMSE "
        "over the head crop's vertices between the source's and the target's offsets (mm); "
        "mean, 95th percentile and maximum over frames; vertex max: the largest single-vertex "
        "error of the take. `arkit` is the source's own set (a floor).",
        "",
        "| head | set | controls | alpha (cm^2) | mesh mean (mm) | mesh p95 (mm) | mesh max (mm) "
        "| vertex max (mm) | cardinality | roughness | ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for head, sets in results.items():
        if head not in HEADS:
            continue
        for name, r in sets.items():
            lines.append(
                f"| {head} | {name} | {r['n_controls']} | {r['alpha']:g} | "
                f"{r['mesh_mean_mm']:.3f} | {r['mesh_p95_mm']:.3f} | {r['mesh_max_mm']:.3f} | "
                f"{r['vertex_max_mm']:.2f} | {r['cardinality']:.1f} | {r['roughness']:.2f} | "
                f"{r['ms_per_frame']:.2f} |"
            )
    motion = {h: s[SETS[0]]["source_motion_mean_mm"] for h, s in results.items() if h in HEADS}
    lines += [
        "",
        "Source motion (mean per-frame RMSE of the ARKit offsets from the neutral): "
        + ", ".join(f"{h} {m:.2f} mm" for h, m in motion.items())
        + ". Timings on a shared 2-core CPU, compiled calls.",
        "",
        f"`{command}`",
    ]
    return "\n".join(lines) + "\n"


def plot(curves: dict, path: Path) -> None:
    fig, axes = plt.subplots(1, len(curves), figsize=(5.5 * len(curves), 3.4), squeeze=False)
    for ax, (head, sets) in zip(axes[0], curves.items(), strict=True):
        for name, rmse in sets.items():
            ax.plot(np.arange(rmse.size) / 60.0, rmse, label=name, lw=1.2)
        ax.set(title=head, xlabel="time (s, 60 fps frames)", ylabel="per-frame RMSE (mm)")
        ax.legend(frameon=False)
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--quick", action="store_true", help="one head, 40 frames, 40 poses")
    args = parser.parse_args(argv)
    command = experiment_command(__file__, argv)
    capture = load_livelinkface(args.data_dir)
    heads = dict(list(HEADS.items())[:1]) if args.quick else HEADS
    results, curves = {}, {}
    for head, stem in heads.items():
        path = data_file(f"rocketbox/{stem}_facial.fbx", args.data_dir)
        rig = load_fbx_rig(path, names="all", crop="head")
        source = select_control_set(rig, "arkit")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # every ARKit channel is present; none is dropped
            take = capture.weights_for(source.names)
        take = take[:40] if args.quick else take
        rng = np.random.default_rng(0)
        n_poses = 40 if args.quick else TRAIN_POSES
        poses = random_sparse_poses(rng, n_poses, source.names)
        results[head], curves[head] = {}, {}
        for name in SETS:
            target = select_control_set(rig, name)
            alpha, sweep = choose_alpha(source, target, poses)
            row, rmse = measure(source, target, take, inverse.QuarticNewton(alpha=alpha))
            row["alpha_sweep"] = sweep
            results[head][name], curves[head][name] = row, rmse
            print(f"{head} {name}: { ({k: v for k, v in row.items() if k != 'alpha_sweep'}) }")
    results["protocol"] = {
        "method": "QuarticNewton (defaults), frames independent",
        "alpha_rule": f"select_alpha (tolerance {TOLERANCE}) over {list(ALPHAS)} cm^2 on "
        f"{TRAIN_POSES} random_sparse_poses of the source ARKit rig (seed 0)",
        "mesh_error": "per-frame RMSE over the head crop's vertices of target minus source "
        "offsets from the neutral (mm); mean / p95 / max over frames",
        "provenance": provenance(command),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    update_results(args.out, "retarget", results, table=table(results, command, n_poses))
    plot(curves, args.out / "retarget_error.png")
    record_command(args.out, command)
    print(f"wrote {args.out / 'results.json'}, table.md and retarget_error.png")


if __name__ == "__main__":
    run_watched(main, "experiments/inverse_rig_retarget.py")
