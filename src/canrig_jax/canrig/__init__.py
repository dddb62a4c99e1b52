"""CANRig (Mohammadi, Weiss et al.): geodesic influence masks, masked cross-attention with
zero-preserving MLPs, the shape-preserving variant, training on real rig shapes."""

from .attention import masked_attention_weights, masked_cross_attention
from .data import (
    EVAL_FALLOFF_PER_CM,
    RADII_CM,
    ExampleOptions,
    Examples,
    TrainingSet,
    build_training_set,
    capture_mixes_of,
    evaluate_poses,
    farthest_point_vertices,
    held_out_poses,
    nearby_poses,
    sample_examples,
    split_capture,
)
from .layout import DENSE, BlockLayout, DenseLayout, Layout, block_layout
from .masks import (
    CLAMP,
    correlation_edge_factor,
    edge_graph,
    influence_mask,
    mesh_edges,
    weighted_geodesic_distance,
)
from .mlp import ZeroPreservingMLP
from .model import AbstractCANRig, Architecture, CANRig, ShapePreservingCANRig, parameter_count
from .rig import HandleEdit, Handles, NeuralRig, deform, edit_mask, trace_edit
from .train import (
    TrainOptions,
    TrainResult,
    load_checkpoint,
    load_model,
    save_checkpoint,
    train,
    train_step,
)

__all__ = [
    "DENSE",
    "AbstractCANRig",
    "Architecture",
    "BlockLayout",
    "DenseLayout",
    "HandleEdit",
    "Layout",
    "block_layout",
    "edit_mask",
    "CLAMP",
    "EVAL_FALLOFF_PER_CM",
    "RADII_CM",
    "CANRig",
    "ExampleOptions",
    "Examples",
    "Handles",
    "NeuralRig",
    "ShapePreservingCANRig",
    "TrainOptions",
    "TrainResult",
    "TrainingSet",
    "ZeroPreservingMLP",
    "build_training_set",
    "capture_mixes_of",
    "correlation_edge_factor",
    "deform",
    "trace_edit",
    "edge_graph",
    "evaluate_poses",
    "farthest_point_vertices",
    "influence_mask",
    "load_checkpoint",
    "load_model",
    "masked_attention_weights",
    "masked_cross_attention",
    "mesh_edges",
    "nearby_poses",
    "parameter_count",
    "sample_examples",
    "save_checkpoint",
    "split_capture",
    "held_out_poses",
    "train",
    "train_step",
    "weighted_geodesic_distance",
]
