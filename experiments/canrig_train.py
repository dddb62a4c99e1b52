"""Train the shape-preserving CANRig on the ict-quartic rig (ICT face part, real shapes).

    python experiments/canrig_train.py --out experiments/results/canrig --minutes 25

Writes DIR/checkpoint.eqx (atomic; rerunning the command resumes from it; the training and
data-building options are stored in it, and a resume with other options is refused),
DIR/train.json (steps, minutes, parameters, loss history, provenance) and
DIR/training_loss.png. Every field of ``TrainOptions``, its ``ExampleOptions`` and
``DataOptions`` is an option ``--field-name`` (``--help`` lists them).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._checkpoint import parameter_count
from canrig_jax._io import save_json
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.canrig import TrainOptions, train
from canrig_jax.canrig._data import DataOptions
from canrig_jax.data import load_livelinkface
from canrig_jax.distributed import add_process_options, initialize_from_args
from canrig_jax.papers.canrig import add_training_options, split_capture, training_options_from_args
from canrig_jax.render import save_figure
from canrig_jax.rig import ict_quartic_rig
from canrig_jax.watchdog import run_watched


def parser() -> argparse.ArgumentParser:
    """The command line: a few script flags, then every field of ``TrainOptions`` (and its
    ``ExampleOptions``) and of ``DataOptions`` as ``--field-name``
    (``canrig_jax.canrig.add_training_options``)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    p.add_argument("--quick", action="store_true", help="tiny data, 30 steps")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        help="data-parallel training over N devices of every process (default: all)",
    )
    add_process_options(p)
    return add_training_options(p)


def options_from_args(args: argparse.Namespace) -> tuple[TrainOptions, DataOptions]:
    return training_options_from_args(args, quick=args.quick)


def main(argv=None):
    args = parser().parse_args(argv)
    group = initialize_from_args(args)  # several processes: first, before any JAX work
    options, data_options = options_from_args(args)
    command = experiment_command(__file__, argv)

    start = time.perf_counter()
    rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    capture_train, _ = split_capture(capture)
    data = data_options.build(rig, capture_train, seed=options.seed)
    print(
        f"training set: {data.shapes.shape[0]} shapes, built in {time.perf_counter() - start:.1f} s"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    result = train(
        data,
        options,
        checkpoint=args.out / "checkpoint.eqx",
        progress=not args.no_progress,
        data_options={**data_options.to_dict(), "seed": options.seed},
        devices=args.devices,
    )
    if not group.is_main:  # process 0 writes the outputs
        return None
    summary = {
        "variant": options.variant,
        "steps": result.step,
        "train_minutes": result.seconds / 60.0,
        "parameters": parameter_count(result.model),
        "training_shapes": int(data.shapes.shape[0]),
        "data": data_options.to_dict(),
        "options": dataclasses.asdict(options),
        "history": result.history,
        "provenance": provenance(command),
    }
    save_json(args.out / "train.json", summary)

    steps = np.array([h["step"] for h in result.history])
    error = np.array([h["error_mm"] for h in result.history])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(steps, error, lw=0.6, alpha=0.5, label="per logged batch")
    if len(error) >= 20:
        smooth = np.convolve(error, np.ones(20) / 20, mode="valid")
        ax.plot(steps[19:], smooth, lw=1.5, label="running mean (20)")
    ax.set_xlabel("step")
    ax.set_ylabel("mean error on sampled vertices (mm)")
    ax.set_yscale("log")
    ax.legend()
    save_figure(fig, args.out / "training_loss.png")
    print(
        f"{result.step} steps, {result.seconds / 60:.1f} min, {summary['parameters']} parameters; "
        f"wrote {args.out}/checkpoint.eqx, train.json, training_loss.png"
    )
    return summary


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
