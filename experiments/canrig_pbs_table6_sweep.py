"""Table 6 on the whole head with K mouth handles for each K (a variant; the protocol has 60):
its reach floor and every method's mouth difference, added to a ``canrig_pbs.py`` results
folder.

    python experiments/canrig_pbs_table6_sweep.py --out experiments/results/canrig_pbs \
        --counts 60 120 200 400

Needs OUT's trained checkpoints (``canrig_pbs_train.py``; a missing network's column is left
out). Adds ``table6_handle_sweep`` to OUT's results.json and its section to table.md (a rerun
replaces it; the rest is kept) and this command to OUT/COMMAND
(``canrig_jax.papers.canrig.whole_head.table6_sweep``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.papers.canrig.whole_head import (
    MODELS_DIR,
    SWEEP_HEADER,
    SWEEP_PROTOCOL,
    add_whole_head_options,
    dialogue_clips,
    pbs_training_set,
    sweep_markdown,
    table6_sweep,
    whole_head,
    whole_head_options_from_args,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument(
        "--counts", type=int, nargs="+", required=True, metavar="K", help="mouth handles"
    )
    parser.add_argument("--no-progress", action="store_true", help="print no progress lines")
    add_whole_head_options(parser)
    args = parser.parse_args(argv)
    if min(args.counts) < 1:
        parser.error(f"--counts: expected counts >= 1, got {args.counts}")
    command = experiment_command(__file__, argv)
    say = (lambda *_: None) if args.no_progress else print
    head = whole_head(whole_head_options_from_args(args), args.data_dir, progress=say)
    data, distances = pbs_training_set(head)
    clips = dialogue_clips(head, 6 if args.quick else 45)
    models = args.out / MODELS_DIR
    sweep = table6_sweep(head, data, distances, models, clips, args.counts, progress=say)
    path = args.out / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    results["table6_handle_sweep"] = {
        "mouth_difference_mm": sweep,
        "protocol": SWEEP_PROTOCOL,
        "provenance": provenance(command),
    }
    save_json(path, results)
    section = sweep_markdown(sweep, command)
    table = args.out / "table.md"
    text = table.read_text() if table.exists() else ""
    save_text(table, text.split(SWEEP_HEADER)[0].rstrip("\n") + "\n\n" + section + "\n")
    record_command(args.out, command)
    print(section)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
