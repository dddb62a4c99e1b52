"""Compare RigAnyFace checkpoints on validation identities, neither training nor held-out test
identities, at the held-out resolution: how a model is chosen before its test numbers are read.
Nothing is trained.

    python experiments/autorig_validate.py --out experiments/results/autorig_long \\
        experiments/results/autorig_wide/checkpoint_raf.eqx \\
        experiments/results/autorig_long/checkpoint_raf.eqx

Validation identities are the held-out stream of seed + 1000 (``VALIDATION_SEED_OFFSET``):
no training identity (stream [seed, 0]) and no test identity (stream [seed, 1]) is among
them. Each checkpoint (row "<folder>/<file stem>"), no motion and deformation transfer (plain
and anchored per each mode of ``--anchors``; a residual checkpoint on each of those bases,
"+<key>_base") are compared by pose class and vertex class (``class_errors``) and per shape
(``heldout_shapes``: does the upper face move?). Writes DIR/validation.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from canrig_jax._io import save_json
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.autorig import ict_autorig_dataset
from canrig_jax.papers.riganyface import (
    ANCHOR_CM,
    ANCHOR_MODES,
    HELDOUT_SPLIT,
    STATIC_MM,
    anchored_base_key,
    class_errors,
    heldout_predictions,
    heldout_shapes,
    load_checkpoint_rows,
)
from canrig_jax.watchdog import run_watched

VALIDATION_SEED_OFFSET = 1000
"""Validation identities are the held-out stream of seed + this."""


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", metavar="CHECKPOINT")
    parser.add_argument("--out", type=Path, required=True, help="folder of validation.json")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--validation-identities", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0, help="the standard run's seed")
    parser.add_argument(
        "--anchors",
        nargs="+",
        choices=ANCHOR_MODES,
        default=["vertex"],
        help="anchored DT bases to compare (transfer_poses(anchor=): per vertex, per part, "
        "per vertex on the skin and per part elsewhere); default: %(default)s",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    models = {name: model for name, (model, _) in load_checkpoint_rows(args.checkpoints).items()}
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=1,
        n_test=args.validation_identities,
        seed=args.seed + VALIDATION_SEED_OFFSET,
        progress=not args.no_progress,
    )
    predicted, truth = heldout_predictions(dataset, models, args.anchors)
    results = {
        "validation": {
            name: class_errors(p, truth, dataset.poses) for name, p in predicted.items()
        },
        "validation_shapes": heldout_shapes(dataset.test[HELDOUT_SPLIT], predicted, dataset.poses),
        "protocol": {
            "identities": f"held-out stream of seed {args.seed + VALIDATION_SEED_OFFSET} "
            f"(not training, not test), {len(truth)} heads",
            "split": HELDOUT_SPLIT,
            "static_mm": STATIC_MM,
            "bases": "a residual checkpoint's row uses plain deformation transfer as its base; "
            f"'+anchored_base' rows anchored DT (static_below = {ANCHOR_CM} cm)",
            "anchors": {
                anchored_base_key(m): f"transfer_poses(static_below={ANCHOR_CM}, anchor={m!r})"
                for m in args.anchors
            },
        },
        "provenance": provenance(experiment_command(__file__, argv)),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "validation.json", results)
    for name, classes in results["validation"].items():
        print(
            name,
            " ".join(
                f"{c}: mae {v['mae_mm']:.4f} static {v['static_mae_mm']:.4f} "
                f"moving {v['moving_mae_mm']:.4f}"
                for c, v in classes.items()
            ),
        )
    upper = np.asarray(results["validation_shapes"]["upper_face"])
    for name, e in results["validation_shapes"]["methods"].items():
        peak = np.asarray(e["peak_ratio"])
        print(
            f"{name} median peak ratio: upper face {np.median(peak[upper]):.2f}, "
            f"lower face {np.median(peak[~upper]):.2f}"
        )
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
