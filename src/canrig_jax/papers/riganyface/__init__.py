"""The RigAnyFace evaluation (Ma et al.; ``experiments/autorig*.py``, ``any_head*.py``):

- the training recipes of the evaluated models (``PURE_MODELS``, ``RESIDUAL_MODEL``,
  ``ANCHORED_RESIDUAL_MODELS``, ``RECIPE_MODELS``, ``RAF_LOSSES``; ``add_recipe_arguments``,
  ``recipe_options``, ``recipe_base``, ``recipe_training_set``, ``train_checkpoint``,
  ``checkpoint_record``);
- their deformation-transfer bases (plain and anchored below ``ANCHOR_CM`` per one of
  ``ANCHOR_MODES``: ``transfer_bases``, ``cached_transfer``, ``anchored_base_key``) and each
  row's rig on a head (``generate_rows``);
- the held-out ICT identities (``HELDOUT_SPLIT``; ``evaluation_rows``, ``evaluate_splits``,
  ``heldout_predictions``, ``load_checkpoint_rows``, ``heldout_shapes``,
  ``clean_penetration``, ``placement_errors`` on heads cut below the chin,
  ``crop_below_chin`` at ``CHIN_LANDMARK``), scored by pose class and vertex class
  (``class_errors`` with ``STATIC_MM``, ``worst_poses``);
- the MakeHuman head, evaluation only (``evaluate_makehuman``, ``FACE_PLACED`` rows,
  ``makehuman_shapes``; ARKit shapes matched by ``shared_shape_matrix``);
- a generated rig as a product (``rig_timing``, ``gltf_round_trip``);
- any head, ``auto_rig``'s methods on heads sculpted by other people (``SculptedHead``,
  ``ict_sculpted_heads``, ``sculpted_head_errors``): few-shot style (``EXAMPLE_ORDER``,
  ``FEW_SHOT_KS``, ``few_shot_rows``, ``mean_few_shot``), a template of the same style
  (``template_row``), the face crop (``face_crop``, ``face_crop_fit``), every axis-aligned
  orientation (``orientation_cases``), the command line's time (``measure_cli_seconds``) and
  the rule that chose the default method (``choose_default_method``);
- 2D supervision (``SUPERVISION_2D_RUNS``, ``parse_supervision_2d_args``,
  ``supervision_2d_options``, ``rigged_heads``, ``padded_faces``, ``chunk_overflow``,
  ``train_2d_run``, ``evaluate_2d``, the rasteriser's ``rasteriser_checks``);
- the tables and figures (``autorig_table``, ``any_head_table``, ``supervision_2d_table``,
  ``plot_training_history``, ``plot_pose_examples``, ``plot_shape_ratios``).
"""

from ...autorig._data import ANCHOR_MODES
from ...autorig._evaluation import STATIC_MM, class_errors, shared_shape_matrix, worst_poses
from ...autorig._methods import ANCHOR_CM
from ...autorig._rocketbox import SculptedHead
from ...autorig._supervision_2d import padded_faces
from ._any_head import (
    EXAMPLE_ORDER,
    FEW_SHOT_KS,
    any_head_table,
    choose_default_method,
    face_crop_fit,
    few_shot_rows,
    ict_sculpted_heads,
    mean_few_shot,
    measure_cli_seconds,
    orientation_cases,
    sculpted_head_errors,
    template_row,
)
from ._bases import anchored_base_key, cached_transfer, generate_rows, transfer_bases
from ._crops import CHIN_LANDMARK, crop_below_chin, face_crop
from ._generation import gltf_round_trip, rig_timing
from ._heldout import (
    HELDOUT_SPLIT,
    clean_penetration,
    evaluate_splits,
    evaluation_rows,
    heldout_predictions,
    heldout_shapes,
    load_checkpoint_rows,
    placement_errors,
)
from ._makehuman import FACE_PLACED, evaluate_makehuman, makehuman_shapes
from ._recipes import (
    ANCHORED_RESIDUAL_MODELS,
    PURE_MODELS,
    RAF_LOSSES,
    RECIPE_MODELS,
    RESIDUAL_MODEL,
    add_recipe_arguments,
    checkpoint_record,
    recipe_base,
    recipe_options,
    recipe_training_set,
    train_checkpoint,
)
from ._report import autorig_table, plot_pose_examples, plot_shape_ratios, plot_training_history
from ._supervision_2d import (
    SUPERVISION_2D_RUNS,
    chunk_overflow,
    evaluate_2d,
    parse_supervision_2d_args,
    rasteriser_checks,
    rigged_heads,
    supervision_2d_options,
    supervision_2d_table,
    train_2d_run,
)

__all__ = [
    "ANCHORED_RESIDUAL_MODELS",
    "ANCHOR_CM",
    "ANCHOR_MODES",
    "CHIN_LANDMARK",
    "EXAMPLE_ORDER",
    "FACE_PLACED",
    "FEW_SHOT_KS",
    "HELDOUT_SPLIT",
    "PURE_MODELS",
    "RAF_LOSSES",
    "RECIPE_MODELS",
    "RESIDUAL_MODEL",
    "STATIC_MM",
    "SUPERVISION_2D_RUNS",
    "SculptedHead",
    "add_recipe_arguments",
    "anchored_base_key",
    "any_head_table",
    "autorig_table",
    "cached_transfer",
    "checkpoint_record",
    "choose_default_method",
    "chunk_overflow",
    "class_errors",
    "clean_penetration",
    "crop_below_chin",
    "evaluate_2d",
    "evaluate_makehuman",
    "evaluate_splits",
    "evaluation_rows",
    "face_crop",
    "face_crop_fit",
    "few_shot_rows",
    "generate_rows",
    "gltf_round_trip",
    "heldout_predictions",
    "heldout_shapes",
    "ict_sculpted_heads",
    "load_checkpoint_rows",
    "makehuman_shapes",
    "mean_few_shot",
    "measure_cli_seconds",
    "orientation_cases",
    "padded_faces",
    "parse_supervision_2d_args",
    "placement_errors",
    "plot_pose_examples",
    "plot_shape_ratios",
    "plot_training_history",
    "rasteriser_checks",
    "recipe_base",
    "recipe_options",
    "recipe_training_set",
    "rig_timing",
    "rigged_heads",
    "sculpted_head_errors",
    "shared_shape_matrix",
    "supervision_2d_options",
    "supervision_2d_table",
    "template_row",
    "train_2d_run",
    "train_checkpoint",
    "transfer_bases",
    "worst_poses",
]
