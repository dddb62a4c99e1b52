"""How long does generating a rig take? Re-measures the rig generation time of the standard
run's ``raf`` checkpoint on the generic ICT head decimated to ~1,750 vertices: cold (compile
+ operators + network) and warm (a new head of similar size), ``papers.riganyface.rig_timing``.

    python experiments/autorig_timing.py --out experiments/results/autorig

Reads DIR/results.json and DIR/checkpoint_raf.eqx (made by ``experiments/autorig.py``),
rewrites the ``rig_seconds`` key of DIR/results.json (the rest is kept) and DIR/table.md.
Timings depend on the machine and its load: run it on a quiet one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.autorig import load_riganyface
from canrig_jax.data import load_ict
from canrig_jax.papers.riganyface import autorig_table, rig_timing
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the standard run's folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    args = parser.parse_args(argv)
    path, checkpoint = args.out / "results.json", args.out / "checkpoint_raf.eqx"
    if not path.exists() or not checkpoint.exists():
        raise ValueError(
            f"--out: needs results.json and checkpoint_raf.eqx in {args.out}; run "
            "experiments/autorig.py there first"
        )
    results = json.loads(path.read_text())
    model, poses, _ = load_riganyface(checkpoint)
    results["rig_seconds"] = rig_timing(model, poses, load_ict(args.data_dir, parts=None))
    results["timing_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    text = autorig_table(results)
    save_text(args.out / "table.md", text)
    print(text)
    print(f"rewrote rig_seconds of {path} and table.md")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
