"""The RigAnyFace training recipes of the auto-rigging experiments: the pure models and their
losses, the deformation transfer + learned residual models (on plain or anchored transfer),
each model's options from one command line, its training set, and one resumable training run
into a checkpoint.

``experiments/autorig.py`` (every model, then the evaluation) and ``experiments/
autorig_train.py`` (one model) share these, so that a checkpoint trained by one resumes in the
other with the same options.
"""

import argparse
import dataclasses
from pathlib import Path

from jaxtyping import ArrayLike, Float

from ..._checkpoint import parameter_count
from ...autorig._data import ANCHOR_MODES, AutorigDataset, PoseSet
from ...autorig._methods import ANCHOR_CM
from ...autorig._model import RigAnyFace
from ...autorig._train import (
    RigAnyFaceTrainOptions,
    TrainingSet,
    augmented_heads,
    load_riganyface,
    train_riganyface,
    training_set,
)
from ._bases import anchored_base_key, cached_transfer

PURE_MODELS = {"raf": {}, "raf_no_global_encoder": {"global_size": 0}}
"""The pure RigAnyFace models (no base) by name, with their options apart from the recipe's:
the paper's model and its step-matched ablation without the global encoder."""

RAF_LOSSES = {
    "squared": {"loss": "squared", "static_weight": 0.0},
    "euclidean_static": {"loss": "euclidean", "static_weight": 1.0},
    "squared_static": {"loss": "squared", "static_weight": 1.0},
    "euclidean": {"loss": "euclidean", "static_weight": 0.0},
    "squared_static_balanced": {"loss": "squared", "static_weight": 1.0, "balance_poses": 1.0},
    "squared_static_half_balanced": {
        "loss": "squared",
        "static_weight": 1.0,
        "balance_poses": 0.5,
    },
    "squared_static_balanced_0.3": {"loss": "squared", "static_weight": 1.0, "balance_poses": 0.3},
}
"""Losses of the pure models (``--raf-loss``), as ``RigAnyFaceTrainOptions`` fields: the
squared loss (the first recipe), the per-vertex Euclidean loss plus the static-vertex term,
the two other combinations of loss and static term, and squared + static with every pose
weighed against its own no-motion error (``balance_poses``: 1, 0.5 and 0.3 of the way)."""

RESIDUAL_MODEL = "raf_dt_residual"
"""The deformation transfer + learned residual model trained on plain deformation transfer."""

ANCHORED_RESIDUAL_MODELS = {
    "raf_anchored_dt_residual": "vertex",
    **{f"raf_anchored_{mode}_dt_residual": mode for mode in ANCHOR_MODES if mode != "vertex"},
}
"""Residual models trained on anchored deformation transfer, by name: the anchoring mode of
their base (``transfer_poses(static_below=ANCHOR_CM, anchor=)``)."""

RESIDUAL_OPTIONS = {"residual": True, "loss": "euclidean", "static_weight": 1.0}
"""Options of every residual model apart from the recipe's (the static weight is
``--residual-static-weight``'s)."""

RECIPE_MODELS = (*PURE_MODELS, RESIDUAL_MODEL, *ANCHORED_RESIDUAL_MODELS)
"""Every model a recipe trains, by name."""


def add_recipe_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the training recipe's options to ``parser``: the data (``--data-dir``,
    ``--train-identities``, ``--seed``, ``--cache``), the budget (``--steps``, ``--minutes``,
    ``--residual-steps``, ``--quick``), the pure models' loss and size (``--raf-loss``,
    ``--raf-width``, ``--raf-conditional-blocks``), the residual models' gate and static term,
    ``--learning-rate``, ``--devices`` and ``--no-progress``. Returns ``parser``; read a
    model's options back with ``recipe_options``."""
    add = parser.add_argument
    add("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    add("--quick", action="store_true", help="2 identities, 20 steps (tests)")
    add(
        "--minutes",
        type=float,
        default=None,
        help="training-time budget per model (accumulated over resumed runs; default: none, "
        "the cosine schedule runs to --steps)",
    )
    add("--steps", type=int, default=2500, help="step budget per model")
    add("--train-identities", type=int, default=24)
    add("--learning-rate", type=float, default=1e-3)
    add(
        "--residual-steps",
        type=int,
        default=2000,
        help="steps of the DT + residual model (its cosine schedule ends there; no clock cut)",
    )
    add("--cache", type=Path, default=None, help="cache of transferred poses")
    add("--seed", type=int, default=0)
    add("--no-progress", action="store_true")
    add(
        "--devices",
        type=int,
        default=None,
        help="data-parallel training over N devices (default: all; see canrig_jax._sharding)",
    )
    add(
        "--raf-loss",
        choices=tuple(RAF_LOSSES),
        default="squared",
        help="loss of raf and raf_no_global_encoder (default: %(default)s, the standard "
        "checkpoints' recipe)",
    )
    add(
        "--raf-width",
        type=int,
        default=RigAnyFaceTrainOptions.width,
        help="feature width of raf and raf_no_global_encoder (default: %(default)s)",
    )
    add(
        "--raf-conditional-blocks",
        type=int,
        default=RigAnyFaceTrainOptions.n_conditional,
        help="pose-conditioned diffusion blocks of raf and raf_no_global_encoder (default: "
        "%(default)s)",
    )
    add(
        "--residual-gate",
        type=float,
        default=0.0,
        help="tau (unit-sphere units) of the residual models' gate on their correction, "
        "|b|^2 / (|b|^2 + tau^2) with b the DT displacement: what DT leaves still stays "
        "still (default: 0, no gate)",
    )
    _add_robust_arguments(add)
    add(
        "--residual-static-weight",
        type=float,
        default=RESIDUAL_OPTIONS["static_weight"],
        help="weight of the residual models' static-vertex term (default: %(default)s)",
    )
    return parser


def _add_robust_arguments(add) -> None:
    """The pure models' fine-tuning, warp and mesh-quality flags (``add_recipe_arguments``)."""
    add(
        "--init-from",
        default=None,
        help="fine-tune raf / raf_no_global_encoder from this RigAnyFace checkpoint (e.g. the "
        "packaged model, canrig_jax.autorig.DEFAULT_CHECKPOINT); its width must be --raf-width",
    )
    add(
        "--warp-copies",
        type=int,
        default=0,
        help="smoothly warped copies of each training head added to a pure model's training "
        "set (stylised proportions and a low-frequency displacement field; default: none)",
    )
    add(
        "--warp-amplitude",
        type=float,
        default=RigAnyFaceTrainOptions.warp_amplitude,
        help="standard deviation of the warp's RBF weights, cm (default: %(default)s)",
    )
    add(
        "--warp-proportions",
        type=float,
        default=RigAnyFaceTrainOptions.warp_proportions,
        help="standard deviation of the warp's log scale per axis (default: %(default)s)",
    )
    add(
        "--warp-targets",
        choices=("warped", "transfer"),
        default="warped",
        help="targets of the warped copies: the warped ICT truth, or anchored deformation "
        "transfer onto the warped head (distillation; --cache keeps it)",
    )
    add(
        "--flip-weight",
        type=float,
        default=0.0,
        help="weight of the pure models' flipped-triangle penalty (default: 0, none)",
    )
    add(
        "--flip-margin",
        type=float,
        default=RigAnyFaceTrainOptions.flip_margin,
        help="cosine from which the flip penalty starts (default: %(default)s)",
    )
    add(
        "--stretch-weight",
        type=float,
        default=0.0,
        help="weight of the pure models' edge-stretch penalty (default: 0, none)",
    )
    add(
        "--stretch-margin",
        type=float,
        default=RigAnyFaceTrainOptions.stretch_margin,
        help="|log edge-length ratio| free of the stretch penalty (default: %(default)s)",
    )


def recipe_options(args: argparse.Namespace, name: str | None = None) -> RigAnyFaceTrainOptions:
    """The training options of model ``name`` (one of ``RECIPE_MODELS``) from a namespace
    parsed by ``add_recipe_arguments``' parser, or with ``name=None`` the options every model
    starts from (results.json's ``config.options``).

    Shared: ``--steps`` (20 with ``--quick``), 200 warm-up steps (5), ``--minutes`` (none),
    ``--learning-rate``, ``--seed``, a checkpoint every 200 steps (10). A pure model adds its
    ``PURE_MODELS`` entry, the ``--raf-loss`` entry of ``RAF_LOSSES``, ``--raf-width`` and
    ``--raf-conditional-blocks``; a residual model ``RESIDUAL_OPTIONS`` with
    ``--residual-static-weight`` and ``--residual-gate``, ``--residual-steps`` steps (20), a
    tenth of them (at most 200) to warm up (5), and no clock limit."""
    if name is not None and name not in RECIPE_MODELS:
        raise ValueError(f"name: expected one of {RECIPE_MODELS}, got {name!r}")
    quick = args.quick
    options = RigAnyFaceTrainOptions(
        steps=20 if quick else args.steps,
        warmup_steps=5 if quick else 200,
        max_minutes=None if quick else args.minutes,
        learning_rate=args.learning_rate,
        seed=args.seed,
        checkpoint_every=10 if quick else 200,
    )
    if name is None:
        return options
    if name in PURE_MODELS:
        return dataclasses.replace(
            options,
            **RAF_LOSSES[args.raf_loss],
            width=args.raf_width,
            n_conditional=args.raf_conditional_blocks,
            **PURE_MODELS[name],
            **_robust_options(args),
        )
    return dataclasses.replace(
        options,
        **{**RESIDUAL_OPTIONS, "static_weight": args.residual_static_weight},
        residual_gate=args.residual_gate,
        steps=20 if quick else args.residual_steps,
        warmup_steps=5 if quick else min(200, args.residual_steps // 10),
        max_minutes=None,
    )


def _robust_options(args: argparse.Namespace) -> dict:
    """The pure models' mesh-quality, warp and fine-tuning options (their defaults when the
    parser predates them)."""
    names = {"init_from": None, "warp_copies": 0, "warp_amplitude": 1.0,
             "warp_proportions": 0.1, "warp_targets": "warped", "flip_weight": 0.0,
             "flip_margin": 0.5,
             "stretch_weight": 0.0, "stretch_margin": 0.25}  # fmt: skip
    out = {name: getattr(args, name, default) for name, default in names.items()}
    if out["init_from"] is not None:
        out["init_from"] = str(out["init_from"])
    return out


def recipe_base(name: str) -> str | None:
    """The evaluation row of model ``name``'s base: None for a pure model,
    ``"deformation_transfer"`` for ``RESIDUAL_MODEL``, ``"deformation_transfer_<key>"`` for
    an anchored residual model (``anchored_base_key`` of its mode)."""
    if name in PURE_MODELS:
        return None
    if name == RESIDUAL_MODEL:
        return "deformation_transfer"
    if name in ANCHORED_RESIDUAL_MODELS:
        return "deformation_transfer_" + anchored_base_key(ANCHORED_RESIDUAL_MODELS[name])
    raise ValueError(f"name: expected one of {RECIPE_MODELS}, got {name!r}")


def recipe_training_set(
    dataset: AutorigDataset,
    name: str,
    *,
    k: int,
    cache: str | Path | None = None,
    seed: int = 0,
    progress: bool = True,
    options: RigAnyFaceTrainOptions | None = None,
) -> TrainingSet:
    """The training set of model ``name`` on ``dataset.train`` (``training_set`` with ``k``
    eigenvectors): the heads alone for a pure model; for a residual model also each head's
    deformation-transfer poses as the base (plain, or anchored per its mode below
    ``ANCHOR_CM``), through ``cached_transfer(cache=, seed=)``. ``options``: a pure model's
    training heads are ``augmented_heads(dataset.train, options)`` (its warped copies; with
    ``warp_targets="transfer"`` their targets anchored transfer, through ``cached_transfer``)."""
    if recipe_base(name) is None:
        heads = dataset.train if options is None else augmented_heads(dataset.train, options)
        if options is not None and options.warp_targets == "transfer":
            # distillation: the warped copies learn anchored transfer, not the warped truth
            n = len(dataset.train)
            heads = heads[:n] + [
                dataclasses.replace(
                    h, displacements=cached_transfer(dataset, h, cache, seed, ANCHOR_CM)
                )
                for h in heads[n:]
            ]
        return training_set(heads, dataset.poses, k=k, progress=progress)
    mode = ANCHORED_RESIDUAL_MODELS.get(name)
    base: list[Float[ArrayLike, "P _V 3"]] = [
        cached_transfer(
            dataset,
            head,
            cache,
            seed,
            None if mode is None else ANCHOR_CM,
            anchor=mode or "vertex",
        )
        for head in dataset.train
    ]
    return training_set(dataset.train, dataset.poses, k=k, progress=progress, base=base)


def checkpoint_record(model: RigAnyFace, header: dict) -> dict:
    """What results.json's ``training`` records of a model from its checkpoint's header
    (``load_riganyface``): steps, minutes, trainable parameters, the last logged training-batch
    error (mm), the training history (for the loss figure) and the options."""
    return {
        "steps": header["step"],
        "minutes": header["seconds"] / 60,
        "parameters": parameter_count(model),
        "final_train_error_mm": header["history"][-1]["error_mm"],
        "history": header["history"],
        "options": header["options"],
    }


def train_checkpoint(
    path: str | Path,
    data: TrainingSet,
    poses: PoseSet,
    options: RigAnyFaceTrainOptions,
    *,
    progress: bool = True,
    devices: int | None = None,
) -> tuple[RigAnyFace, dict]:
    """Train (or resume) the checkpoint at ``path`` (``train_riganyface``) and read it back:
    (the model, its record as ``checkpoint_record``'s, with this run's step count, accumulated
    minutes and ``options``). A finished checkpoint resumes without training."""
    result = train_riganyface(
        data, poses, options, checkpoint=path, progress=progress, devices=devices
    )
    model, _, header = load_riganyface(path)
    name = Path(path).stem.removeprefix("checkpoint_")
    print(f"{name}: {result.step} steps in {result.seconds / 60:.1f} min")
    return model, {
        **checkpoint_record(model, header),
        "steps": result.step,
        "minutes": result.seconds / 60,
        "options": options.to_dict(),
    }
