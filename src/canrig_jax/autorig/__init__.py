"""RigAnyFace building blocks: DiffusionNet in equinox, features and pooling."""

from .diffusion import LearnedDiffusion, implicit_diffusion, spectral_diffusion
from .diffusion_net import DiffusionNet, DiffusionNetBlock, SpatialGradientFeatures
from .features import heat_kernel_signature, hks_times, mass_weighted_mean

__all__ = [
    "DiffusionNet",
    "DiffusionNetBlock",
    "LearnedDiffusion",
    "SpatialGradientFeatures",
    "heat_kernel_signature",
    "hks_times",
    "implicit_diffusion",
    "mass_weighted_mean",
    "spectral_diffusion",
]
