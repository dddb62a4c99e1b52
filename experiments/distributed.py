"""Throughput with one and two processes (``jax.distributed``) on this machine, and what two
processes give against one.

    python experiments/distributed.py --out experiments/results/distributed

Configurations, each a fresh run, all in this run (the ratios are against ``1 process`` of the
same run): ``1 process``; ``2 processes`` (``canrig launch -n 2``; both processes may use both
cores); and, to show what one core does, ``1 process, 1 core`` and ``2 processes, 1 core
each`` (each process pinned with ``os.sched_setaffinity`` before JAX starts, so XLA's thread
pool has one core).

Workloads, each timed after a warm-up call compiled it (wall clock of the whole run, best of
two; the 2-core machine is shared):

- inverse rig: ``inverse.QuarticNewton(alpha=0.1 cm^2)`` on the ict-quartic rig at the 180
  Live Link Face frames, ``solve_sequence(..., across_processes=True)`` (chunks of
  ``inverse.FRAMES_PER_CALL`` frames shared over the processes) -> frames per second;
- training: ``canrig.train`` (default model and examples: 8 per step, 384 sampled vertices;
  50-100 handles) on a small ict-quartic set (48 capture frames, 48 random poses), each
  step's examples split over every process's device -> steps per second (a step is the
  whole batch, whatever the processes);
- auto-rig: the packaged RigAnyFace model on two ICT identities' heads,
  ``autorig.auto_rig_heads(..., across_processes=True)`` -> heads per minute.

Each run's weights, trained parameters and rigs are compared with ``1 process``'s: the
inverse weights (max |difference|), the trained parameters and the rigs' displacements
(relative norm of the difference).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from canrig_jax.papers import canrig as canrig_paper

CONFIGS = {
    "1 process": (1, False),
    "2 processes": (2, False),
    "1 process, 1 core": (1, True),
    "2 processes, 1 core each": (2, True),
}
"""name -> (processes, pinned to one core each)."""

ALPHA_CM2 = 0.1
TRAIN_STEPS = 20


def _best(fn, repeats: int = 2) -> tuple[float, object]:
    """(the shortest wall time of ``repeats`` calls, the last result); a call compiles first."""
    import jax

    out = jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times), out


def worker(out: Path, pinned: bool) -> None:
    """One process of a configuration: measure every workload; process 0 writes ``out``."""
    if pinned:
        index = int(os.environ.get("CANRIG_PROCESS_ID", "0"))
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[index % os.cpu_count()]})
    import equinox as eqx
    import jax

    from canrig_jax import autorig, canrig, distributed, inverse
    from canrig_jax.data import ict_identity, load_ict, load_livelinkface
    from canrig_jax.rig import evaluate_batch, ict_quartic_rig

    group = distributed.initialize()
    rig, _ = ict_quartic_rig(progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning)
        take = load_livelinkface().weights_for(rig.names, missing="zero")
    problem = inverse.prepare(rig)
    targets = np.asarray(evaluate_batch(rig, take))
    method = inverse.QuarticNewton(alpha=ALPHA_CM2)
    seconds, solution = _best(
        lambda: inverse.solve_sequence(problem, targets, method, across_processes=True)
    )
    record = {"inverse_seconds": seconds, "inverse_frames": len(take)}
    arrays = {"weights": np.asarray(solution.weights)}

    capture, _ = canrig_paper.split_capture(take[:48])
    data = canrig.build_training_set(rig, capture, n_random=48, n_pool=400, seed=0)
    # the default examples (8 per step, 384 vertices), 50-100 handles: one compiled shape
    examples = canrig.ExampleOptions(n_handles=(50, 100), handle_bucket=100)
    options = canrig.TrainOptions(steps=TRAIN_STEPS, log_every=TRAIN_STEPS, examples=examples)
    canrig.train(data, options, progress=False, stop_after=1)  # compiles the step
    start = time.perf_counter()
    trained = canrig.train(data, options, progress=False)
    record["train_seconds"], record["train_steps"] = time.perf_counter() - start, TRAIN_STEPS
    leaves = jax.tree_util.tree_leaves(eqx.filter(trained.model, eqx.is_array))
    arrays["params"] = np.concatenate([np.asarray(x, np.float64).ravel() for x in leaves])

    ict = load_ict(parts=None)
    coefficients = np.random.default_rng(11).standard_normal((2, 100))
    heads = [(ict_identity(c, model=ict), np.asarray(ict.faces)) for c in coefficients]
    start = time.perf_counter()
    rigs = autorig.auto_rig_heads(heads, method=autorig.RigAnyFaceNetwork(), across_processes=True)
    record["autorig_seconds"], record["autorig_heads"] = time.perf_counter() - start, len(heads)
    arrays["rigs"] = np.stack([np.asarray(r.rig.deltas) for r in rigs])
    if group.is_main:
        out.mkdir(parents=True, exist_ok=True)
        np.savez(out / "arrays.npz", **arrays)
        record["processes"], record["cores_each"] = group.processes, len(os.sched_getaffinity(0))
        (out / "record.json").write_text(json.dumps(record))


def run_config(name: str, folder: Path) -> dict:
    """Run one configuration in fresh processes; its record and arrays."""
    processes, pinned = CONFIGS[name]
    out = folder / name.replace(" ", "_").replace(",", "")
    command = [sys.executable, __file__, "--worker", str(out)] + (["--pinned"] if pinned else [])
    if processes > 1:
        command = [sys.executable, "-m", "canrig_jax._commands", "launch", "-n", str(processes),
                   "--", *command]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("CANRIG_PROCESS")}
    env.pop("CANRIG_COORDINATOR", None)
    start = time.perf_counter()
    subprocess.run(command, env={**env, "JAX_PLATFORMS": "cpu"}, check=True, timeout=900)
    record = json.loads((out / "record.json").read_text())
    record["run_seconds"] = time.perf_counter() - start
    return record | {"arrays": dict(np.load(out / "arrays.npz"))}


def rates(record: dict) -> dict:
    return {
        "inverse_frames_per_s": record["inverse_frames"] / record["inverse_seconds"],
        "train_steps_per_s": record["train_steps"] / record["train_seconds"],
        "autorig_heads_per_min": 60 * record["autorig_heads"] / record["autorig_seconds"],
    }


def compare(record: dict, reference: dict) -> dict:
    a, b = record["arrays"], reference["arrays"]

    def relative(x, y):
        return float(np.linalg.norm(x - y) / np.linalg.norm(y))

    return {
        "inverse_weights_max_abs": float(np.max(np.abs(a["weights"] - b["weights"]))),
        "params_relative": relative(a["params"], b["params"]),
        "rigs_relative": relative(a["rigs"].astype(np.float64), b["rigs"]),
    }


def table(rows: dict) -> str:
    lines = [
        "## Throughput with one and two processes (2 shared CPU cores)",
        "",
        "Per run (whole batch), and its ratio to `1 process` measured in the same run.",
        "",
        "| configuration | inverse rig (frames/s) | training (steps/s) | auto-rig (heads/min) "
        "| run (s) | weights max abs diff | params rel. diff | rigs rel. diff |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in rows.items():
        r, ratio, d = row["rates"], row["ratio"], row["difference"]
        cells = [f"{r[k]:.3g} ({ratio[k]:.2f}x)" for k in r]
        lines.append(
            f"| {name} | {' | '.join(cells)} | {row['run_seconds']:.0f} "
            f"| {d['inverse_weights_max_abs']:.1e} | {d['params_relative']:.1e} "
            f"| {d['rigs_relative']:.1e} |"
        )
    lines += [
        "",
        "Per process (the run's throughput divided by its processes):",
        "",
        "| configuration | inverse rig (frames/s) | training (steps/s) | auto-rig (heads/min) |",
        "|---|---|---|---|",
    ]
    for name, row in rows.items():
        cells = [f"{v / row['processes']:.3g}" for v in row["rates"].values()]
        lines.append(f"| {name} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--pinned", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--configs", nargs="+", choices=tuple(CONFIGS), default=tuple(CONFIGS))
    args = parser.parse_args(argv)
    if args.worker is not None:
        worker(args.worker, args.pinned)
        return 0
    if args.out is None:
        parser.error("--out is required")
    from canrig_jax._io import save_results
    from canrig_jax._provenance import experiment_command, provenance, record_command

    command = experiment_command(__file__, argv)
    configs = ["1 process", *[c for c in args.configs if c != "1 process"]]
    with tempfile.TemporaryDirectory() as tmp:
        records = {}
        for name in configs:
            records[name] = run_config(name, Path(tmp))
            print(f"{name}: {rates(records[name])}", flush=True)
    reference = rates(records["1 process"])
    rows = {}
    for name, record in records.items():
        r = rates(record)
        rows[name] = {
            "processes": record["processes"],
            "cores_each": record["cores_each"],
            "rates": r,
            "ratio": {k: r[k] / reference[k] for k in r},
            "difference": compare(record, records["1 process"]),
            "run_seconds": record["run_seconds"],
        }
    text = table(rows)
    print(text)
    results = {"configurations": rows, "cpu_count": os.cpu_count(), **provenance(command)}
    save_results(args.out, {"distributed": results}, text)
    record_command(args.out, command)
    print(f"wrote {args.out}/results.json, table.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
