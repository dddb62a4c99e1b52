"""CANRig dialogue replacement on the ict-quartic rig (Figure 12) with Table 6's
global-blendshape baselines, added to a ``canrig_workflows.py`` results folder.

    python experiments/canrig_workflows_dialogue.py \
        --checkpoint experiments/results/canrig_workflows/model/checkpoint.eqx \
        --out experiments/results/canrig_workflows

The source clip (capture frames 90-134) takes the mouth of the target clip (135-179) inside
the mouth mask: CANRig direct and fitted at 60 mouth handles, and the global-blendshape
baselines (``canrig_jax.papers.canrig.workflows.dialogue_table``). Updates OUT's
results.json (``dialogue``, ``timing.dialogue_ms_per_frame``), table.md and dialogue.png; the
rest is kept. ``--rig local-fit`` rebuilds the ``LocalFitRig`` that OUT's ``canrig_workflows.py
--rig local-fit`` run selected.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._metrics import CM_TO_MM
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax._timing import median_ms
from canrig_jax.canrig import FitOptions, dialogue_replacement, expression_region
from canrig_jax.papers.canrig.workflows import (
    DIALOGUE_RADIUS_CM,
    FALLOFF_PER_CM,
    MOUTH_THRESHOLD_CM,
    dialogue_table,
    local_fit_from_selection,
    network_rig,
    workflow_data,
    workflows_markdown,
)
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.watchdog import run_watched


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, help="CANRig checkpoint (--rig network)")
    parser.add_argument(
        "--out", type=Path, required=True, help="a canrig_workflows.py results folder"
    )
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="6 frames instead of 45")
    parser.add_argument("--fit-steps", type=int, default=FitOptions().max_steps)
    parser.add_argument("--lsmr-steps", type=int, default=FitOptions().lsmr_steps)
    parser.add_argument("--seed", type=int, default=0, help="the GBS-19 basis's poses")
    parser.add_argument(
        "--rig",
        choices=("network", "local-fit"),
        default="network",
        help="network: the CANRig checkpoint; local-fit: the LocalFitRig OUT's run selected",
    )
    return parser


def main(argv=None):
    parser = _parser()
    args = parser.parse_args(argv)
    if args.rig == "network" and args.checkpoint is None:
        parser.error("--checkpoint: required with --rig network")
    path = args.out / "results.json"
    if not path.exists():
        parser.error(f"--out: no results.json in {args.out} (run canrig_workflows.py first)")
    results = json.loads(path.read_text())
    options = FitOptions(max_steps=args.fit_steps, lsmr_steps=args.lsmr_steps)
    data = workflow_data(args.data_dir)
    quartic = data.quartic
    if args.rig == "local-fit":
        model = results["protocol"]["model"]
        if "selected" not in model:
            parser.error(f"--rig local-fit: {path} holds no LocalFitRig selection")
        rig = local_fit_from_selection(quartic, data.capture, model["selected"])
    else:
        rig, _ = network_rig(args.checkpoint, quartic)

    mouth = expression_region(quartic, threshold=MOUTH_THRESHOLD_CM)
    n_frames = 6 if args.quick else 45
    dialogue, run = dialogue_table(rig, quartic, data.capture, mouth, options, n_frames, args.seed)
    print(f"dialogue: {dialogue}")
    per_clip_ms = median_ms(
        lambda: dialogue_replacement(
            rig, run.source, run.target, run.handles, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM
        ),
        repeats=3,
    )
    results["dialogue"] = dialogue
    results.setdefault("timing", {})["dialogue_ms_per_frame"] = per_clip_ms / len(run.source)
    results["dialogue_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    table = workflows_markdown(results)
    save_text(args.out / "table.md", table)
    _figure(rig, run, mouth, args.out / "dialogue.png")
    print(table)
    return results


def _error_mm(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1) * CM_TO_MM


def _figure(rig, run, mouth, path):
    """Figure 12 analog at the middle frame: the mouth mask and handles, the target, the
    direct result's error to the target and its change from the source."""
    source, target, out = run.source, run.target, run.outputs["direct"]
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
    axes[0].scatter(*source[f][run.handles.index][:, :2].T, s=4, c="red")
    panels = (
        (target[f], _error_mm(target[f], source[f]), "target frame (vs source)"),
        (out[f], _error_mm(out[f], target[f]), "replaced (error to target)"),
        (out[f], _error_mm(out[f], source[f]), "change from source"),
    )
    for ax, (shape, value, title) in zip(axes[1:], panels, strict=True):
        mapper = plot_vertex_scalar(ax, shape, rig.faces, value, vmax=10.0, title=title)
    fig.colorbar(mapper, ax=axes[1:], shrink=0.7, label="mm")
    fig.suptitle("dialogue replacement (Figure 12 analog): handles in red")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
