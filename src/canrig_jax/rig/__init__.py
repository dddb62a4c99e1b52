"""The blendshape rig of any corrective order, corrective synthesis, the ict-quartic rig."""

from .blendshape import BlendshapeRig, Corrective, check_weights, combination_coefficients, evaluate
from .ict_quartic import ict_linear_rig, ict_quartic_rig
from .io import load_rig, save_rig
from .synthesis import (
    MUTUALLY_EXCLUSIVE,
    SynthesisOptions,
    SynthesisReport,
    overlapping_pairs,
    synthesize_correctives,
)

__all__ = [
    "MUTUALLY_EXCLUSIVE",
    "BlendshapeRig",
    "Corrective",
    "SynthesisOptions",
    "SynthesisReport",
    "check_weights",
    "combination_coefficients",
    "evaluate",
    "ict_linear_rig",
    "ict_quartic_rig",
    "load_rig",
    "overlapping_pairs",
    "save_rig",
    "synthesize_correctives",
]
