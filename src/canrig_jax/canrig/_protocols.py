"""Evaluation protocols of the CANRig experiments that are more than orchestration: the
training command line derived from the option dataclasses, the check that a saved PBS model
matches the run that resumes or evaluates it, and Table 6's reach floor.

The experiment scripts (``experiments/canrig_train.py``, ``experiments/canrig_pbs.py``) call
these; the tests call them here.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float, Int

from .._cli import add_dataclass_options, from_args
from .._metrics import CM_TO_MM
from ._data import FARTHEST_METRICS, DataOptions
from ._pbs import PatchLayout
from ._train import LOSSES, VARIANTS, TrainOptions

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


def check_pbs_training_matches(
    folder: str | Path,
    *,
    handles_on: str,
    graph: str,
    attach: Sequence[str] = (),
    attach_onto: Sequence[str] = (),
) -> None:
    """Refuse (``ValueError`` naming the flag) to resume or evaluate the PBS model saved in
    ``folder`` with other options than it was trained with: another ``handles_on``, or, for a
    masked model, another ``graph`` (and, on the ``"attached"`` graph, other ``attach`` /
    ``attach_onto`` part names). ``folder/train.json`` says how it was trained (before these
    options existed: ``"skin"`` and ``"mesh"``); without it there is nothing to check. A
    folder named ``shape_transformer*`` holds the Shape Transformer, which has no masks, so
    only ``handles_on`` is checked."""
    folder = Path(folder)
    meta = folder / "train.json"
    if not meta.exists():
        return
    meta = json.loads(meta.read_text())
    run = {"handles_on": handles_on, "graph": graph, "attach": attach, "attach_onto": attach_onto}
    trained = {"handles_on": meta.get("handles_on", "skin")}
    if not folder.name.startswith("shape_transformer"):  # the Shape Transformer has no masks
        trained["graph"] = meta.get("graph", "mesh")
        if trained["graph"] == "attached" and graph == "attached":
            trained["attach"] = meta["attach"]
            trained["attach_onto"] = meta["attach_onto"]
    for name, value in trained.items():
        if name in ("attach", "attach_onto"):
            same = list(value) == list(run[name])
        else:
            same = value == run[name]
        if not same:
            flag = "--" + name.replace("_", "-")
            raise ValueError(
                f"{flag}: {folder} was trained with {flag} {value}, this run uses {run[name]}"
            )


def reach_floor(
    layout: PatchLayout,
    patch_distance_cm: Float[np.ndarray, "P N"],
    handles: Int[np.ndarray, " H"],
    source: Float[np.ndarray, "T N 3"],
    target: Float[np.ndarray, "T N 3"],
    region: Bool[np.ndarray, " N"],
    *,
    reach_cm: float,
) -> tuple[float, int]:
    """Lower bound of a patch-blendshape edit's mean error over ``region`` (Table 6's mouth
    difference), whatever the network: a vertex of ``region`` whose every covering patch is
    seeded farther than ``reach_cm`` (the clamped mask's reach) from every moved handle keeps
    the ``source`` frame, so its error ``|source - target|`` is unavoidable.

    ``patch_distance_cm`` (P, N): geodesic distance in cm from each patch's seed to each
    vertex; ``handles`` (H,): the moved handle vertices; ``source``, ``target`` (T, N, 3) in
    cm; ``region`` (N,). Returns ``(floor_mm, n_unreached)``: the unreached vertices' error
    summed and divided by the number of ``region`` vertices (mm, averaged over the T frames),
    and how many region vertices are unreached."""
    distances = np.asarray(patch_distance_cm)
    region = np.asarray(region, bool)
    handles = np.asarray(handles)
    if distances.ndim != 2 or distances.shape[0] != layout.n_patches:
        raise ValueError(
            f"patch_distance_cm: expected shape ({layout.n_patches}, N), got {distances.shape}"
        )
    if region.shape != distances.shape[1:] or not region.any():
        raise ValueError(f"region: expected a non-empty ({distances.shape[1]},) mask")
    if np.shape(source) != np.shape(target) or np.shape(source)[1:] != (region.size, 3):
        raise ValueError(
            f"source, target: expected the same (T, {region.size}, 3) shape, got "
            f"{np.shape(source)} and {np.shape(target)}"
        )
    if handles.size == 0:
        raise ValueError("handles: expected at least one handle")
    if not reach_cm > 0:
        raise ValueError(f"reach_cm: expected > 0, got {reach_cm}")
    reached_patch = distances[:, handles].min(axis=1) <= reach_cm  # (P,)
    unreached = region & ~layout.covered_by(reached_patch)
    error = np.linalg.norm(np.asarray(source) - np.asarray(target), axis=-1) * CM_TO_MM
    return float(error[:, unreached].sum(axis=1).mean() / region.sum()), int(unreached.sum())
