"""The blendshape rig of any corrective order, its (batched) evaluation, corrective synthesis,
the ict-quartic rig, and rigs carried onto other meshes (remeshing, deformation transfer)."""

from .blendshape import (
    BlendshapeRig,
    Corrective,
    check_weights,
    combination_coefficients,
    evaluate,
    evaluate_batch,
)
from .ict_quartic import ict_linear_rig, ict_quartic_rig
from .io import load_rig, save_rig
from .nonlinear import deformation_gradient_blend
from .synthesis import (
    MUTUALLY_EXCLUSIVE,
    SynthesisOptions,
    SynthesisReport,
    exclusive_pairs,
    overlapping_pairs,
    synthesize_correctives,
)
from .transfer import deformation_transfer, remesh_rig

__all__ = [
    "MUTUALLY_EXCLUSIVE",
    "BlendshapeRig",
    "Corrective",
    "SynthesisOptions",
    "SynthesisReport",
    "check_weights",
    "combination_coefficients",
    "deformation_gradient_blend",
    "deformation_transfer",
    "evaluate",
    "evaluate_batch",
    "exclusive_pairs",
    "ict_linear_rig",
    "ict_quartic_rig",
    "load_rig",
    "overlapping_pairs",
    "remesh_rig",
    "save_rig",
    "synthesize_correctives",
]
