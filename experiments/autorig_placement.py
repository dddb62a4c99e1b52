"""Does RigAnyFace need the head placed as in training? The standard run's ``raf`` checkpoint
placed in the unit sphere by the bounding box (as trained) and by ``face_placement`` (from the
fitted face), on the held-out heads whole and cut 1 cm below the chin, as a face scan would be.
Nothing is trained.

    python experiments/autorig_placement.py --out experiments/results/autorig

Reads DIR/results.json and DIR/checkpoint_raf.eqx (made by ``experiments/autorig.py``),
rewrites the ``placement`` and ``placement_protocol`` keys of DIR/results.json (the rest is
kept) and DIR/table.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.autorig import ict_autorig_dataset, load_riganyface
from canrig_jax.papers.riganyface import autorig_table, placement_errors
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the standard run's folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    path, checkpoint = args.out / "results.json", args.out / "checkpoint_raf.eqx"
    if not path.exists() or not checkpoint.exists():
        raise ValueError(
            f"--out: needs results.json and checkpoint_raf.eqx in {args.out}; run "
            "experiments/autorig.py there first"
        )
    results = json.loads(path.read_text())
    config = results["config"]
    model, poses, _ = load_riganyface(checkpoint)
    dataset = ict_autorig_dataset(  # held-out identities have their own random stream
        args.data_dir,
        n_train=1,
        n_test=config["test_identities"],
        seed=config["options"]["seed"],
        progress=not args.no_progress,
    )
    results["placement"], results["placement_protocol"] = placement_errors(model, poses, dataset)
    results["placement_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    text = autorig_table(results)
    save_text(args.out / "table.md", text)
    print(text)
    print(f"rewrote the placement of {path} and table.md")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
