"""RigAnyFace: DiffusionNet in equinox, the FACS-conditioned auto-rigger, its data and metrics."""

from .data import (
    AutorigDataset,
    PoseSet,
    RiggedHead,
    ict_autorig_dataset,
    make_head,
    pose_displacements,
    quartic_pose_set,
    transfer_poses,
)
from .diffusion import (
    LearnedDiffusion,
    implicit_diffusion,
    spectral_diffusion,
    spectral_diffusion_and_gradient,
)
from .diffusion_net import DiffusionNet, DiffusionNetBlock, SpatialGradientFeatures
from .features import heat_kernel_signature, hks_times, mass_weighted_mean
from .metrics import error_stats, outside_fraction, penetration, winding_numbers
from .model import ConditionalBlock, RigAnyFace, normalise
from .rig import GeneratedRig, generate_rig, predict_displacements, rig_from_poses
from .train import TrainOptions, TrainResult, load_model, train, training_set

__all__ = [
    "AutorigDataset",
    "ConditionalBlock",
    "DiffusionNet",
    "DiffusionNetBlock",
    "GeneratedRig",
    "LearnedDiffusion",
    "PoseSet",
    "RigAnyFace",
    "RiggedHead",
    "SpatialGradientFeatures",
    "TrainOptions",
    "TrainResult",
    "error_stats",
    "generate_rig",
    "predict_displacements",
    "heat_kernel_signature",
    "hks_times",
    "ict_autorig_dataset",
    "implicit_diffusion",
    "load_model",
    "make_head",
    "mass_weighted_mean",
    "normalise",
    "outside_fraction",
    "penetration",
    "pose_displacements",
    "quartic_pose_set",
    "rig_from_poses",
    "spectral_diffusion",
    "spectral_diffusion_and_gradient",
    "train",
    "training_set",
    "transfer_poses",
    "winding_numbers",
]
