"""How long does ``canrig autorig`` take on a head from another source? Re-measures, with the
library's default method now, the command end to end in fresh processes on the any-head
experiment's heads (a held-out ICT identity, both Rocketbox heads, MakeHuman; warm, and on
MakeHuman once with an empty cache: ``papers.riganyface.measure_cli_seconds``).

    python experiments/any_head_seconds.py --out experiments/results/any_head

Rewrites the ``seconds``, ``library_default`` and ``provenance_seconds`` keys of
DIR/results.json (made by ``experiments/any_head.py``; the rest is kept) and DIR/table.md, and
adds its command to DIR/COMMAND. Timings depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import DEFAULT_METHOD, load_makehuman, load_rocketbox_head
from canrig_jax.papers.riganyface import (
    SculptedHead,
    any_head_table,
    ict_sculpted_heads,
    measure_cli_seconds,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="experiments/results/any_head")
    parser.add_argument("--data-dir")
    args = parser.parse_args(argv)
    out = Path(args.out)
    path = out / "results.json"
    if not path.exists():
        raise ValueError(f"--out: no results.json in {out}; run experiments/any_head.py first")
    command = experiment_command(__file__, argv)
    start = time.perf_counter()

    def log(message):
        print(f"[{time.perf_counter() - start:7.1f} s] {message}", flush=True)

    warnings.simplefilter("ignore")
    mh = load_makehuman(args.data_dir)
    heads = {
        "ict_heldout": ict_sculpted_heads(1, args.data_dir)[0],
        "rocketbox_female": load_rocketbox_head("Female_Adult_01", args.data_dir),
        "rocketbox_male": load_rocketbox_head("Male_Adult_08", args.data_dir),
        "makehuman": SculptedHead("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names),
    }
    results = json.loads(path.read_text())
    results["seconds"] = measure_cli_seconds(heads, log)
    results["library_default"] = DEFAULT_METHOD.name
    results["provenance_seconds"] = provenance(command)
    save_json(path, results)
    save_text(out / "table.md", any_head_table(results))
    record_command(out, command, "re-measured the command's time with its new default")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
