"""Do the generated rigs push teeth, gums or eyeballs through the skin where the ground truth
does not? With the standard run's checkpoints, every held-out row's penetration on the pose
set where the ground truth has none (``papers.riganyface.clean_penetration``: per head, the inner
vertices inside the skin at rest and the poses whose ground truth pushes none of them out),
and the plain penetration re-measured next to it. Nothing is trained; no training data is
built.

    python experiments/autorig_penetration.py --out experiments/results/autorig

Reads DIR/results.json and the checkpoints of ``raf``, ``raf_no_global_encoder``,
``raf_dt_residual`` (and of any residual model on anchored deformation transfer found there),
made by ``experiments/autorig.py``; rewrites the ``penetration_clean``,
``penetration_clean_protocol`` and ``penetration_remeasured`` keys of DIR/results.json (the
rest is kept) and DIR/table.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.autorig import ict_autorig_dataset, load_riganyface
from canrig_jax.papers.riganyface import (
    ANCHORED_RESIDUAL_MODELS,
    PURE_MODELS,
    RESIDUAL_MODEL,
    autorig_table,
    clean_penetration,
    evaluation_rows,
    heldout_predictions,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the standard run's folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    path = args.out / "results.json"
    names = [*PURE_MODELS, RESIDUAL_MODEL]
    missing = [n for n in names if not (args.out / f"checkpoint_{n}.eqx").exists()]
    if not path.exists() or missing:
        raise ValueError(
            f"--out: needs results.json and the checkpoints of {names} in {args.out}; run "
            "experiments/autorig.py there first"
        )
    anchors = ["vertex"]
    for name, mode in ANCHORED_RESIDUAL_MODELS.items():
        if (args.out / f"checkpoint_{name}.eqx").exists():
            names.append(name)
            anchors += [] if mode in anchors else [mode]
    results = json.loads(path.read_text())
    config = results["config"]
    models = {n: load_riganyface(args.out / f"checkpoint_{n}.eqx")[0] for n in names}
    dataset = ict_autorig_dataset(  # held-out identities have their own random stream
        args.data_dir,
        n_train=1,
        n_test=config["test_identities"],
        seed=config["options"]["seed"],
        progress=not args.no_progress,
    )
    predicted, _ = heldout_predictions(dataset, models, anchors, rows=evaluation_rows(models))
    heads, part_names = dataset.test["unseen_topology"], dataset.head.part_names
    results.update(clean_penetration(heads, predicted, dataset.poses, part_names))
    results["penetration_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    text = autorig_table(results)
    save_text(args.out / "table.md", text)
    print(text)
    print(f"rewrote the penetration of {path} and table.md")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
