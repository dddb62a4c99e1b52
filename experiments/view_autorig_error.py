"""RigAnyFace's error on the MakeHuman head as a vertex-coloured glb for ``canrig view``.

The default RigAnyFace checkpoint (``autorig.DEFAULT_CHECKPOINT``) generates a rig for the
MakeHuman hm08 head (evaluation only: never trained on); each vertex is coloured by its mean
error, in mm, against the person-made ARKit targets over the shapes both rigs share (white 0,
red at the skin's 95th percentile and above). The rig is animated by the Live Link capture, so
a user can scrub the take and turn the head around the worst vertex:

    python experiments/view_autorig_error.py --out experiments/results/view_autorig_error
    canrig view experiments/results/view_autorig_error/error.glb

Writes DIR/error.glb (not committed: about 8 MB, rebuilt in under a minute), DIR/error.png
(a headless screenshot at the take's most-open jaw, when Chromium is installed),
DIR/results.json and DIR/COMMAND.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from canrig_jax._io import save_json
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import (
    DEFAULT_CHECKPOINT,
    RigAnyFaceNetwork,
    load_makehuman,
    load_riganyface,
)
from canrig_jax.data import load_livelinkface
from canrig_jax.papers.riganyface import shared_shape_matrix
from canrig_jax.rig import export_animated_gltf
from canrig_jax.viewer import error_colors, find_chromium, screenshot_glb
from canrig_jax.watchdog import run_watched


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=DEFAULT_CHECKPOINT,
        help="RigAnyFace checkpoint (default: the default model, %(default)s)",
    )
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    record_command(args.out, command)

    head = load_makehuman(args.data_dir)
    model, poses, _ = load_riganyface(args.checkpoint)
    rig = RigAnyFaceNetwork((model, poses)).generate(head.neutral, head.faces).rig
    target_index, matrix = shared_shape_matrix(rig.names, head.names)
    predicted = np.einsum("sk,kvd->svd", matrix, np.asarray(rig.deltas))
    truth = head.deltas[target_index]
    per_shape_mm = np.linalg.norm(predicted - truth, axis=-1) * CM_TO_MM  # (S, V)
    error_mm = per_shape_mm.mean(axis=0)
    skin = head.skin
    vmax = float(np.percentile(error_mm[skin], 95))
    worst = int(np.argmax(np.where(skin, error_mm, -1)))
    shape_of_worst = [head.names[i] for i in target_index][int(np.argmax(per_shape_mm[:, worst]))]

    capture = load_livelinkface(args.data_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TongueOut: no ICT shape (reported by canrig animate)
        weights = capture.weights_for(rig.names)
    frames = np.asarray(capture.frame_number, float)
    times = (frames - frames[0]) / float(capture.fps)
    glb = export_animated_gltf(
        rig,
        weights,
        args.out / "error.glb",
        times=times,
        vertex_colors=error_colors(error_mm, vmax),
    )
    jaw = np.asarray(capture.weights)[:, list(capture.names).index("JawOpen")]
    shown_at = float(times[np.argmax(jaw)])
    screenshot = None
    if find_chromium() is not None:
        shot = screenshot_glb(glb, args.out / "error.png", time=shown_at)
        screenshot = {"file": "error.png", "time_s": shot.time, "page_errors": shot.errors}

    results = {
        "head": "MakeHuman hm08 (evaluation only), 4,920 vertices, cm",
        "checkpoint": f"{args.checkpoint.parent.name}/{args.checkpoint.name}",
        "shared_shapes": len(target_index),
        "colour": "mean over shared shapes of the per-vertex error (mm); white 0, red >= vmax",
        "vmax_mm_skin_p95": vmax,
        "skin_mean_mm": float(error_mm[skin].mean()),
        "skin_max_mm": float(error_mm[skin].max()),
        "worst_vertex": worst,
        "worst_vertex_position_cm": head.neutral[worst].tolist(),
        "worst_vertex_largest_shape": shape_of_worst,
        "take": f"Live Link capture, {len(times)} keys, no head rotation",
        "glb": {"file": "error.glb", "bytes": glb.stat().st_size, "committed": False},
        "screenshot": screenshot,
        "provenance": provenance(command),
    }
    save_json(args.out / "results.json", results)
    print(
        f"skin error per vertex (mean over {len(target_index)} shapes): mean "
        f"{results['skin_mean_mm']:.3f} mm, max {results['skin_max_mm']:.3f} mm at vertex "
        f"{worst} ({shape_of_worst}); red from {vmax:.3f} mm; wrote {glb}"
    )


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
