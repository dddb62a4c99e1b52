"""Train one whole-head PBS model (CANRig-PBS, a Figure 8 variant or the Shape Transformer)
for ``canrig_pbs.py``'s evaluation.

    python experiments/canrig_pbs_train.py --out experiments/results/canrig_pbs \
        --model per_patch --steps 4000 --decay-steps 4000

Trains into OUT/models/MODEL[TAG]/checkpoint.eqx (resumable: the same command continues a
run and reproduces an uninterrupted one) with its train.json, on the whole head of
``canrig_jax.papers.canrig.whole_head.whole_head`` (the same options as the evaluation's).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from canrig_jax._io import save_json
from canrig_jax._provenance import experiment_command, provenance
from canrig_jax.distributed import add_process_options, initialize_from_args
from canrig_jax.papers.canrig.whole_head import (
    MODELS_DIR,
    add_whole_head_options,
    check_model_matches,
    pbs_training_set,
    whole_head,
    whole_head_options_from_args,
)
from canrig_jax.pbs import PBS_MODELS, PBSTrainOptions, train_pbs
from canrig_jax.watchdog import run_watched


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument("--model", choices=PBS_MODELS, required=True, help="the model trained")
    parser.add_argument("--minutes", type=float, default=15.0, help="training budget")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--learning-rate", type=float, default=PBSTrainOptions.learning_rate)
    parser.add_argument("--decay-start", type=int, default=0)
    parser.add_argument("--decay-steps", type=int, default=4000)
    parser.add_argument(
        "--tag", default="", help="folder suffix: OUT/models/MODEL+TAG (e.g. Figure 8's runs)"
    )
    parser.add_argument(
        "--local-prior",
        action="store_true",
        help="a CANRig-PBS variant: the network corrects a per-patch masked ridge fit of the "
        "basis to the handles it sees (CANRigPBS local_prior; beyond the paper)",
    )
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--devices",
        type=int,
        default=None,
        help="data-parallel training over N devices of every process (default: all)",
    )
    add_process_options(parser)
    return add_whole_head_options(parser)


def main(argv=None):
    args = _parser().parse_args(argv)
    group = initialize_from_args(args)  # several processes: first, before any JAX work
    head_options = whole_head_options_from_args(args)
    options = PBSTrainOptions(
        model=args.model,
        steps=args.steps,
        max_minutes=args.minutes,
        decay_start=args.decay_start,
        decay_steps=args.decay_steps,
        learning_rate=args.learning_rate,
        local_prior=args.local_prior,
    )
    folder = args.out / MODELS_DIR / (args.model + args.tag)
    check_model_matches(head_options, folder)
    head = whole_head(head_options, args.data_dir)
    data, _ = pbs_training_set(head)
    folder.mkdir(parents=True, exist_ok=True)
    scale = float(np.abs(head.train_shapes - head.neutral).max())
    _, step, seconds, history = train_pbs(
        data,
        options,
        checkpoint=folder / "checkpoint.eqx",
        displacement_scale=scale,
        progress=not args.no_progress,
        devices=args.devices,
    )
    if not group.is_main:  # process 0 writes the outputs
        return
    graph = head_options.graph
    attached = {"attach": list(head_options.attach), "attach_onto": list(head_options.attach_onto)}
    save_json(
        folder / "train.json",
        {
            "model": args.model,
            "steps": step,
            "train_minutes": seconds / 60,
            "options": options.to_dict(),
            "graph": graph,
            **(attached if graph == "attached" else {}),
            "handles_on": head_options.handles_on,
            "history": history,
            "provenance": provenance(experiment_command(__file__, argv)),
        },
    )
    print(f"{args.model}: {step} steps in {seconds / 60:.1f} min")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
