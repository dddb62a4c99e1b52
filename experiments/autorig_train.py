"""Train (or resume) one RigAnyFace checkpoint of the auto-rigging recipe, and nothing else:
a chunk of a long run, or the models of one folder in parallel processes.

    python experiments/autorig_train.py raf --out experiments/results/autorig_long \\
        --raf-loss euclidean_static --raf-width 64 --steps 7000 --train-identities 40

MODEL is a pure model (``raf``, ``raf_no_global_encoder``), the DT + learned residual model
(``raf_dt_residual``) or a residual model on anchored deformation transfer
(``raf_anchored_<mode>_dt_residual``); its options come from the same flags as
``experiments/autorig.py``'s (``canrig_jax.papers.riganyface.recipe_options``), so the standard
command then resumes the finished checkpoint (training no further) and evaluates it. Writes
DIR/checkpoint_<MODEL>.eqx only (no results); a rerun resumes it. ``--cache DIR`` keeps the
training heads' transferred poses (a residual model's base) between runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canrig_jax.autorig import ict_autorig_dataset
from canrig_jax.distributed import add_process_options, initialize_from_args
from canrig_jax.papers.riganyface import (
    RECIPE_MODELS,
    add_recipe_arguments,
    recipe_options,
    recipe_training_set,
    train_checkpoint,
)
from canrig_jax.watchdog import run_watched


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", choices=RECIPE_MODELS, help="the model to train")
    parser.add_argument("--out", type=Path, required=True, help="folder of the checkpoint")
    add_recipe_arguments(parser)
    add_process_options(parser)
    args = parser.parse_args(argv)
    group = initialize_from_args(args)  # several processes: first, before any JAX work
    args.out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    dataset = ict_autorig_dataset(  # one held-out identity: none is used here
        args.data_dir,
        n_train=2 if args.quick else args.train_identities,
        n_test=1,
        seed=args.seed,
        progress=progress,
    )
    options = recipe_options(args, args.model)
    data = recipe_training_set(
        dataset,
        args.model,
        k=options.k,
        cache=args.cache,
        seed=args.seed,
        progress=progress,
        options=options,
    )
    print(f"{data.n_heads} training heads ({data.vertices.shape[1]} padded vertices)")
    path = args.out / f"checkpoint_{args.model}.eqx"
    train_checkpoint(path, data, dataset.poses, options, progress=progress, devices=args.devices)
    if group.is_main:  # process 0 writes the checkpoint
        print(f"wrote {path}")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
