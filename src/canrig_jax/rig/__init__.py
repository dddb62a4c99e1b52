"""The blendshape rig of any corrective order, and corrective synthesis."""

from .blendshape import BlendshapeRig, Corrective, check_weights, combination_coefficients, evaluate

__all__ = ["BlendshapeRig", "Corrective", "check_weights", "combination_coefficients", "evaluate"]
