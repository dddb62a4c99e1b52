"""RigAnyFace: DiffusionNet in equinox, the FACS-conditioned auto-rigger, its data and metrics."""

from ._data import (
    ANCHOR_MODES,
    AutorigDataset,
    PoseSet,
    RiggedHead,
    anchor_parts,
    copy_poses,
    face_placement,
    fit_head_landmarks,
    head_correspondence,
    head_rig,
    ict_autorig_dataset,
    ict_pose_source,
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
from ._evaluation import (
    ACTIVE_MM,
    STATIC_MM,
    class_errors,
    pose_classes,
    sculpted_target_errors,
    shared_shape_matrix,
    static_mask,
    worst_poses,
)
from ._features import heat_kernel_signature, hks_times, mass_weighted_mean
from ._makehuman import MakeHumanHead, load_makehuman
from ._metrics import (
    error_stats,
    inner_outside,
    outside_fraction,
    penetration,
    penetration_free_set,
    winding_numbers,
)
from ._model import ConditionalBlock, RigAnyFace, normalise
from ._orientation import HeadOrientation, head_orientation
from ._rig import (
    DEFAULT_POSE_CHUNK,
    GeneratedRig,
    generate_rig,
    pad_to_bucket,
    predict_displacements,
    rig_from_poses,
)
from ._train import (
    STATIC_CM,
    TrainOptions,
    TrainResult,
    head_inputs,
    load_model,
    make_model,
    static_vertex_error,
    train,
    training_set,
)

__all__ = [
    "ACTIVE_MM",
    "ANCHOR_MODES",
    "anchor_parts",
    "MakeHumanHead",
    "load_makehuman",
    "STATIC_CM",
    "STATIC_MM",
    "class_errors",
    "copy_poses",
    "fit_head_landmarks",
    "face_placement",
    "head_correspondence",
    "pose_classes",
    "sculpted_target_errors",
    "shared_shape_matrix",
    "static_mask",
    "static_vertex_error",
    "worst_poses",
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
    "ict_pose_source",
    "implicit_diffusion",
    "load_model",
    "make_head",
    "mass_weighted_mean",
    "normalise",
    "outside_fraction",
    "penetration",
    "penetration_free_set",
    "inner_outside",
    "HeadOrientation",
    "head_orientation",
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

# 2D supervision (issue 25)
from ._supervision_2d import (  # noqa: E402
    Supervision2DOptions,
    load_model_2d,
    loss_2d,
    padded_faces,
    train_2d,
)

__all__ += ["Supervision2DOptions", "load_model_2d", "loss_2d", "padded_faces", "train_2d"]
