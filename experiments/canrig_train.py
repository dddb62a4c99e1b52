"""Train the shape-preserving CANRig on the ict-quartic rig (ICT face part, real shapes).

    python experiments/canrig_train.py --out experiments/results/canrig --minutes 25

Writes DIR/checkpoint.eqx (atomic; rerunning the command resumes from it), DIR/train.json
(steps, minutes, parameters, loss history) and DIR/training_loss.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax.canrig import (
    ExampleOptions,
    TrainOptions,
    build_training_set,
    parameter_count,
    split_capture,
    train,
)
from canrig_jax.canrig.train import LOSSES
from canrig_jax.data import load_livelinkface
from canrig_jax.io import save_json
from canrig_jax.render import save_figure
from canrig_jax.rig import ict_quartic_rig


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    parser.add_argument("--quick", action="store_true", help="tiny data, 30 steps")
    parser.add_argument("--minutes", type=float, default=25.0, help="training time budget")
    parser.add_argument("--steps", type=int, default=100_000, help="step budget")
    parser.add_argument("--variant", default="shape_preserving", help="or 'canrig'")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--latent", type=int, default=64, help="total latent width (all heads)")
    parser.add_argument("--heads", type=int, default=4, help="attention heads")
    parser.add_argument("--width", type=int, default=64, help="hidden width of every MLP")
    parser.add_argument("--fourier", type=int, default=0, help="octaves of the query encoding")
    parser.add_argument(
        "--farthest-sets", type=int, default=0, help="farthest-point handle sets in the pool"
    )
    parser.add_argument(
        "--farthest-metric",
        default="euclidean",
        choices=("euclidean", "geodesic"),
        help="distance of the farthest-point handle sets (geodesic: the metric of the masks)",
    )
    parser.add_argument("--p-farthest", type=float, default=0.0)
    parser.add_argument("--p-eval-radius", type=float, default=0.0)
    parser.add_argument("--p-capture", type=float, default=None)
    parser.add_argument("--n-active", type=int, nargs=2, default=(4, 10))
    parser.add_argument(
        "--capture-mixes",
        type=int,
        default=0,
        help="extra poses: convex combinations of two training capture frames",
    )
    parser.add_argument(
        "--decay-steps", type=int, default=0, help="cosine learning-rate decay (0: constant)"
    )
    parser.add_argument(
        "--decay-start", type=int, default=0, help="step at which the cosine decay begins"
    )
    parser.add_argument(
        "--decay-floor", type=float, default=0.05, help="final rate / initial rate of the decay"
    )
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument(
        "--loss",
        default="squared",
        choices=LOSSES,
        help="per-vertex penalty: squared error (eq. 3) or the Euclidean error (as reported)",
    )
    parser.add_argument(
        "--interpolation-prior",
        action="store_true",
        help="add the mask-weighted mean of the handle displacements; the network corrects it",
    )
    parser.add_argument(
        "--query-modulation",
        action="store_true",
        help="output input also modulated by an affine map of the vertex's query",
    )
    parser.add_argument(
        "--linear-skip", action="store_true", help="bias-free linear skip in value/output MLPs"
    )
    parser.add_argument("--p-neutral", type=float, default=0.1, help="base shape: the neutral")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    capture_train, _ = split_capture(capture)
    data = build_training_set(
        rig,
        capture_train,
        n_random=50 if args.quick else 800,
        n_pool=256 if args.quick else 2048,
        seed=args.seed,
        n_active=tuple(args.n_active),
        farthest_sets=args.farthest_sets,
        farthest_geodesic=args.farthest_metric == "geodesic",
        capture_mixes=args.capture_mixes,
    )
    print(
        f"training set: {data.shapes.shape[0]} shapes, built in {time.perf_counter() - start:.1f} s"
    )
    options = TrainOptions(
        variant=args.variant,
        n_heads=args.heads,
        latent=args.latent,
        width=args.width,
        fourier=args.fourier,
        linear_skip=args.linear_skip,
        query_modulation=args.query_modulation,
        interpolation_prior=args.interpolation_prior,
        decay_steps=args.decay_steps,
        decay_start=args.decay_start,
        decay_floor=args.decay_floor,
        loss=args.loss,
        steps=30 if args.quick else args.steps,
        max_minutes=None if args.quick else args.minutes,
        seed=args.seed,
        checkpoint_every=10 if args.quick else 250,
        log_every=5 if args.quick else 25,
        examples=ExampleOptions(
            batch=args.batch,
            p_neutral=args.p_neutral,
            p_farthest=args.p_farthest,
            p_eval_radius=args.p_eval_radius,
            p_capture=args.p_capture,
        ),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    result = train(
        data, options, checkpoint=args.out / "checkpoint.eqx", progress=not args.no_progress
    )
    summary = {
        "variant": options.variant,
        "steps": result.step,
        "train_minutes": result.seconds / 60.0,
        "parameters": parameter_count(result.model),
        "training_shapes": int(data.shapes.shape[0]),
        "data": {
            "n_active": list(args.n_active),
            "farthest_sets": args.farthest_sets,
            "farthest_metric": args.farthest_metric,
            "capture_mixes": args.capture_mixes,
        },
        "options": dataclasses.asdict(options),
        "history": result.history,
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
    main()
