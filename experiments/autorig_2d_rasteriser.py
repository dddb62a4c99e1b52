"""Is the differentiable rasteriser right, and how fast is it? Its checks on the generic ICT
head decimated to ~1,750 vertices: the soft rasteriser's gradient against finite differences,
its hard limit and the fast path (``rasterise_hard`` + ``interpolate`` + ``silhouette``)
against NumPy ray casting, the fast path's gradients in float64, and forward + backward frames
per second at 256^2 (``papers.riganyface.rasteriser_checks``).

    python experiments/autorig_2d_rasteriser.py --out experiments/results/autorig_2d

Rewrites the ``rasteriser`` key of DIR/results.json (the rest is kept; a later
``experiments/autorig_2d.py`` run keeps this section) and DIR/table.md. Timings depend on the
machine and its load: run it on a quiet one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.papers.riganyface import rasteriser_checks, supervision_2d_table
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="smaller images (tests)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    path = args.out / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {"provenance": provenance(command)}
    results["rasteriser"] = rasteriser_checks(args.data_dir, args.quick)
    results["rasteriser"]["provenance"] = provenance(command)
    print("rasteriser:", {k: v for k, v in results["rasteriser"].items() if "note" not in k})
    save_json(path, results)
    save_text(args.out / "table.md", supervision_2d_table(results))
    print(f"wrote {path}")
    return results


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
