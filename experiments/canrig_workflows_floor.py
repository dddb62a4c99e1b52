"""The floor of Table 4's random-vertex protocol: the error at the vertices no handle reaches,
in every A-to-B result whatever the network or the fit, added to a ``canrig_workflows.py``
results folder.

    python experiments/canrig_workflows_floor.py \
        --checkpoint experiments/results/canrig_workflows/model/checkpoint.eqx \
        --out experiments/results/canrig_workflows --pairs 1000

The same (A, B) pairs and random handle sets as OUT's Table 4 (``--pairs`` and ``--seed``
must be its own; checked), ``canrig_jax.papers.canrig.workflows.unreached_floor``.
Updates OUT's results.json (``a_to_b_floor``) and table.md; the rest is kept. The rig only
places the handles (geodesic distances) and gives the masks' clamp: ``--rig local-fit``
rebuilds the ``LocalFitRig`` OUT's run selected.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.papers.canrig.workflows import (
    local_fit_from_selection,
    network_rig,
    results_of_the_same_pairs,
    table4_protocol,
    unreached_floor,
    workflow_data,
    workflows_markdown,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, help="CANRig checkpoint (--rig network)")
    parser.add_argument(
        "--out", type=Path, required=True, help="a canrig_workflows.py results folder"
    )
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--pairs", type=int, default=1000, help="OUT's (A, B) pairs")
    parser.add_argument("--seed", type=int, default=0, help="OUT's seed")
    parser.add_argument(
        "--rig",
        choices=("network", "local-fit"),
        default="network",
        help="network: the CANRig checkpoint; local-fit: the LocalFitRig OUT's run selected",
    )
    args = parser.parse_args(argv)
    if args.rig == "network" and args.checkpoint is None:
        parser.error("--checkpoint: required with --rig network")
    path = args.out / "results.json"
    if not path.exists():
        parser.error(f"--out: no results.json in {args.out} (run canrig_workflows.py first)")
    results = results_of_the_same_pairs(path, args.pairs, args.seed, "--pairs, --seed")
    data = workflow_data(args.data_dir)
    if args.rig == "local-fit":
        selected = results["protocol"]["model"].get("selected")
        if selected is None:
            parser.error(f"--rig local-fit: {path} holds no LocalFitRig selection")
        rig = local_fit_from_selection(data.quartic, data.capture, selected)
    else:
        rig, _ = network_rig(args.checkpoint, data.quartic)
    pairs, random_sets, _ = table4_protocol(len(data.shapes), rig.n_vertices, args.pairs, args.seed)
    results["a_to_b_floor"] = {
        "random_vertices": unreached_floor(rig, data.shapes, pairs, random_sets)
    }
    results["a_to_b_floor_provenance"] = provenance(experiment_command(__file__, argv))
    save_json(path, results)
    table = workflows_markdown(results)
    save_text(args.out / "table.md", table)
    print(table)
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
