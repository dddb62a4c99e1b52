"""Train (or resume) one run of the 2D-supervision experiment, and nothing else: a chunk of a
long run, or the two runs in parallel processes.

    python experiments/autorig_2d_train.py 3d_only --out experiments/results/autorig_2d

RUN is ``3d_only`` (3D loss on the rigged heads) or ``2d_unrigged_plus_3d`` (2D loss on every
head, then 3D + 2D on the rigged ones); its options come from the same flags as
``experiments/autorig_2d.py``'s, which then resumes the finished checkpoints (training no
further) and evaluates them. Writes the run's checkpoints in DIR only; a rerun resumes them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canrig_jax.autorig import ict_autorig_dataset, training_set
from canrig_jax.papers.riganyface import (
    SUPERVISION_2D_RUNS,
    chunk_overflow,
    padded_faces,
    parse_supervision_2d_args,
    rigged_heads,
    supervision_2d_options,
    train_2d_run,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", choices=SUPERVISION_2D_RUNS, help="the run to train")
    parser.add_argument("--out", type=Path, required=True, help="folder of the checkpoints")
    args = parse_supervision_2d_args(parser, argv)
    args.out.mkdir(parents=True, exist_ok=True)
    opts2d = supervision_2d_options(args)
    dataset = ict_autorig_dataset(  # one held-out identity: none is used here
        args.data_dir,
        n_train=args.train_identities,
        n_test=1,
        seed=args.seed,
        progress=not args.no_progress,
    )
    heads, rigged = dataset.train, rigged_heads(dataset, args.rigged_identities)
    data = training_set(heads, dataset.poses, k=128, progress=not args.no_progress)
    faces = padded_faces(heads)
    if opts2d.rasteriser == "fast" and args.run != "3d_only":  # 3d_only renders nothing
        overflow = chunk_overflow(data, faces, opts2d)
        print(f"fast rasteriser: chunks over budget on the training heads: {overflow}")
        if overflow:
            raise SystemExit("raise Supervision2DOptions.chunk_budget: some triangles are dropped")
    _, info = train_2d_run(
        args.run,
        data,
        faces,
        dataset.poses,
        rigged,
        opts2d,
        folder=args.out,
        steps=args.steps,
        stage1_fraction=args.stage1_fraction,
        minutes=args.minutes,
        seed=args.seed,
        progress=not args.no_progress,
    )
    print(f"trained {args.run}: {info['steps']} steps, {info['seconds'] / 60:.1f} min")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
