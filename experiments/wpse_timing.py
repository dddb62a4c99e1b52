"""Table 1 analog: training and per-frame run time of WPSE, face and head, P = 10 and 50.

    python experiments/wpse_timing.py --out experiments/results/wpse

Measures the timing rows of the WPSE experiment in --out, whose results.json
``experiments/wpse.py`` wrote: the poses are rebuilt from the seed, the edit frames, budgets,
support tolerance and leave-one-out widths read back from the file (the head is timed unless
the results were ``--quick``). Writes the rows under ``timing`` (the command under
``timing_provenance``) and rewrites table.md; everything else stays as it was. Run it on a
quiet machine; each row records the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import warnings
from pathlib import Path

import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.data import load_livelinkface
from canrig_jax.mesh import DeformationGradientBlend
from canrig_jax.papers import wpse as wpse_paper
from canrig_jax.rig import evaluate_batch, ict_linear_rig, random_sparse_poses
from canrig_jax.watchdog import run_watched

PROBE_FRAMES = 30  # held-out frames each model and the rig run on


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of experiments/wpse.py")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--seed", type=int, default=0, help="the seed experiments/wpse.py had")
    args = parser.parse_args(argv)
    path = args.out / "results.json"
    if not path.exists():
        raise ValueError(f"--out: no results.json in {args.out}; run experiments/wpse.py first")
    results = json.loads(path.read_text())
    protocol = results["protocol"]
    rig = ict_linear_rig(args.data_dir)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    rng = np.random.default_rng(args.seed)
    poses = np.concatenate([capture, random_sparse_poses(rng, protocol["random_poses"], rig.names)])
    if len(poses) != protocol["frames"]:
        raise ValueError(f"--out: {len(poses)} frames, its results.json has {protocol['frames']}")
    edit_frames = np.asarray(protocol["edit_frames"])
    probe = poses[np.setdiff1d(np.arange(len(poses)), edit_frames)][:PROBE_FRAMES]
    parts = {"face": rig}
    if not protocol["quick"]:
        parts["head"] = ict_linear_rig(args.data_dir, parts=None)
    budgets = [int(key.removeprefix("p")) for key in results["errors"]["wpse"]]
    rows = []
    for part, part_rig in parts.items():
        blend = DeformationGradientBlend(part_rig.neutral, part_rig.deltas, part_rig.faces)
        edited = poses[edit_frames]
        edits = blend(edited).astype(np.float32) - np.asarray(evaluate_batch(part_rig, edited))
        for budget in budgets:
            row = wpse_paper.time_edit_model(
                part_rig,
                edited[:budget],
                edits[:budget],
                probe,
                sigma=results["sigma"][f"wpse_p{budget}"]["loo_sigma"],
                support_tol=protocol["support_tol_cm"],
            )
            rows.append({"load_average_1min": os.getloadavg()[0], "part": part, **row})
            print("timing", rows[-1])
    results["timing"] = rows
    results["timing_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    table = wpse_paper.results_table(results)
    save_text(args.out / "table.md", table)
    print(table)
    print(f"wrote the timing rows of {path} and table.md")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
