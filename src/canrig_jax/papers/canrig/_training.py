"""Protocol of the CANRig training experiment that is more than orchestration: the training
command line derived from the option dataclasses (``experiments/canrig_train.py``)."""

import argparse

from ..._cli import add_dataclass_options, from_args
from ...canrig._data import FARTHEST_METRICS, DataOptions
from ...canrig._train import LOSSES, VARIANTS, TrainOptions

_OPTION_ALIASES = {"n_heads": ["--heads"], "max_minutes": ["--minutes"]}
"""Short flags kept from the first version of the training command (committed commands use
them)."""
_OPTION_DEFAULTS = {"steps": 100_000, "max_minutes": 25.0}
"""Where the command line's defaults differ from ``TrainOptions``'s (a time budget decides)."""
_OPTION_CHOICES = {
    "variant": sorted(VARIANTS),
    "loss": LOSSES,
    "farthest_metric": FARTHEST_METRICS,
}
_OPTION_HELP = {
    "max_minutes": "training time budget",
    "steps": "step budget",
    "n_heads": "attention heads",
    "latent": "total latent width (all heads)",
    "width": "hidden width of every MLP",
    "fourier": "octaves of the query encoding",
    "farthest_sets": "farthest-point handle sets in the pool",
    "farthest_metric": "distance of the farthest-point handle sets (geodesic: that of the masks)",
    "capture_mixes": "extra poses: convex combinations of two training capture frames",
    "decay_steps": "cosine learning-rate decay (0: constant)",
    "decay_start": "step at which the cosine decay begins",
    "decay_floor": "final rate / initial rate of the decay",
    "loss": "per-vertex penalty: squared error (eq. 3) or the Euclidean error (as reported)",
    "interpolation_prior": "add the mask-weighted mean of the handle displacements",
    "query_modulation": "output input also modulated by an affine map of the vertex's query",
    "linear_skip": "bias-free linear skip in value/output MLPs",
    "value_position": "value modulation: an MLP of the handle's encoded base position",
    "p_neutral": "base shape: the neutral",
}
_QUICK = {"steps": 30, "max_minutes": None, "checkpoint_every": 10, "log_every": 5}
"""``--quick``: a few steps on the tiny training set (``DataOptions.quick``)."""


def add_training_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add every field of ``TrainOptions`` (and its ``ExampleOptions``) and of ``DataOptions``
    to ``parser`` as ``--field-name`` (booleans as ``--x / --no-x``), with the short flags
    ``--heads`` and ``--minutes``, and a 100,000-step, 25-minute default budget.

    Returns ``parser``. Read the options back with ``training_options_from_args``."""
    for cls in (TrainOptions, DataOptions):
        add_dataclass_options(
            parser,
            cls,
            aliases=_OPTION_ALIASES,
            defaults=_OPTION_DEFAULTS,
            choices=_OPTION_CHOICES,
            help=_OPTION_HELP,
        )
    return parser


def training_options_from_args(
    args: argparse.Namespace, *, quick: bool = False
) -> tuple[TrainOptions, DataOptions]:
    """The ``(TrainOptions, DataOptions)`` a namespace parsed by ``add_training_options``'s
    parser holds; ``quick`` replaces the budget by 30 steps without a time limit (checkpoint
    every 10, log every 5) and the data by ``DataOptions.quick()``."""
    options = from_args(TrainOptions, args, **(_QUICK if quick else {}))
    data_options = from_args(DataOptions, args)
    return options, data_options.quick() if quick else data_options
