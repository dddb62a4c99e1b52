"""CANRig (Mohammadi, Weiss et al.): geodesic influence masks, masked cross-attention with
zero-preserving MLPs, the shape-preserving variant, training on real rig shapes, and the
workflows an artist runs on it (pose A to B direct and fitted, iterative layers, clip editing,
dialogue replacement), all on one family of handle rigs (``AbstractHandleRig``). Patch
blendshapes (PBS) for the whole head are ``canrig_jax.pbs``; the paper's evaluation (held-out
splits, the workflow tables, the training script's options) is ``canrig_jax.papers.canrig``.
"""

from ._data import ExampleOptions, build_training_set
from ._handle_rig import AbstractHandleRig, FitOptions, HandleEdit
from ._layout import influence_reach
from ._masks import CLAMP, correlation_edge_factor, influence_mask
from ._model import CANRig, ShapePreservingCANRig
from ._rig import NeuralRig
from ._train import TrainOptions, load_model, train
from ._workflows import (
    FitSolution,
    clip_edit,
    dialogue_replacement,
    expression_region,
    interior_vertices,
    iterative_layers,
    pose_a_to_b,
)

HANDLE_RIGS = (CANRig, ShapePreservingCANRig)
"""The final handle rigs of this subpackage (``AbstractHandleRig``); ``canrig_jax.pbs``
adds ``LocalFitRig`` and ``PBSRig`` (``canrig_jax.pbs.HANDLE_RIGS`` lists all four, for the
family's contract test)."""

__all__ = [
    "CLAMP",
    "AbstractHandleRig",
    "CANRig",
    "ExampleOptions",
    "FitOptions",
    "FitSolution",
    "HandleEdit",
    "NeuralRig",
    "ShapePreservingCANRig",
    "TrainOptions",
    "build_training_set",
    "clip_edit",
    "correlation_edge_factor",
    "dialogue_replacement",
    "expression_region",
    "influence_mask",
    "influence_reach",
    "interior_vertices",
    "iterative_layers",
    "load_model",
    "pose_a_to_b",
    "train",
]
