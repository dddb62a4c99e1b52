"""RigAnyFace: DiffusionNet in equinox, the FACS-conditioned auto-rigger, its data and metrics."""

from ._data import (
    AutorigDataset,
    PoseSet,
    RiggedHead,
    head_rig,
    ict_autorig_dataset,
    make_head,
    pose_displacements,
    quartic_pose_set,
    transfer_poses,
)
from ._diffusion import (
    LearnedDiffusion,
    implicit_diffusion,
    spectral_diffusion,
    spectral_diffusion_and_gradient,
)
from ._diffusion_net import DiffusionNet, DiffusionNetBlock, SpatialGradientFeatures
from ._features import heat_kernel_signature, hks_times, mass_weighted_mean
from ._metrics import error_stats, outside_fraction, penetration, winding_numbers
from ._model import ConditionalBlock, RigAnyFace, normalise
from ._rig import (
    DEFAULT_POSE_CHUNK,
    GeneratedRig,
    generate_rig,
    pad_to_bucket,
    predict_displacements,
    rig_from_poses,
)
from ._train import (
    TrainOptions,
    TrainResult,
    head_inputs,
    load_model,
    make_model,
    train,
    training_set,
)

__all__ = [
    "DEFAULT_POSE_CHUNK",
    "head_inputs",
    "head_rig",
    "make_model",
    "pad_to_bucket",
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
