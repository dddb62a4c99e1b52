"""The blendshape rig of any corrective order, its (batched) evaluation, corrective synthesis,
the ict-quartic and MakeHuman quartic rigs, and rigs carried onto other meshes (remeshing,
deformation transfer)."""

from ._arkit import arkit_channels, rename_to_arkit
from ._blendshape import (
    UNIT_IN_CM,
    BlendshapeRig,
    Corrective,
    check_weights,
    combination_coefficients,
    evaluate,
    evaluate_batch,
)
from ._control_sets import CONTROL_SETS, control_set_of, select_blendshapes, select_control_set
from ._extras import EXTRA_SHAPES, RPM_EXTRAS, VISEMES, check_extra_sets, with_extra_shapes
from ._fbx import load_fbx_rig
from ._gltf import export_gltf, load_gltf_rig
from ._gltf_animation import (
    export_animated_gltf,
    head_rotation_quaternions,
    morph_target_weights,
)
from ._gltf_avatar import (
    GltfAvatar,
    MeshVertices,
    accessor_array,
    add_morph_targets,
    avatar_from_fbx,
    mesh_vertices,
    node_descendants,
    read_gltf_avatar,
    target_names,
    write_gltf_avatar,
)
from ._gltf_validate import find_gltf_validator, validate_gltf
from ._ict_quartic import ict_linear_rig, ict_quartic_rig
from ._io import load_rig, save_rig
from ._makehuman import makehuman_quartic_rig
from ._nonlinear import deformation_gradient_blend
from ._poses import random_sparse_poses
from ._synthesis import (
    MUTUALLY_EXCLUSIVE,
    SynthesisOptions,
    SynthesisReport,
    exclusive_pairs,
    overlapping_pairs,
    synthesize_correctives,
)
from ._transfer import deformation_transfer, remesh_rig
from ._usd import USD_SUFFIXES, export_usd, load_usd_rig
from ._vrm import (
    REQUIRED_BONES,
    VRM_PRESETS,
    add_vrm_expressions,
    check_humanoid,
    humanoid_bones,
)

__all__ = [
    "USD_SUFFIXES",
    "export_usd",
    "load_usd_rig",
    "REQUIRED_BONES",
    "VRM_PRESETS",
    "add_vrm_expressions",
    "check_humanoid",
    "humanoid_bones",
    "EXTRA_SHAPES",
    "RPM_EXTRAS",
    "VISEMES",
    "check_extra_sets",
    "with_extra_shapes",
    "GltfAvatar",
    "MeshVertices",
    "accessor_array",
    "add_morph_targets",
    "avatar_from_fbx",
    "mesh_vertices",
    "node_descendants",
    "read_gltf_avatar",
    "target_names",
    "write_gltf_avatar",
    "CONTROL_SETS",
    "control_set_of",
    "select_blendshapes",
    "select_control_set",
    "arkit_channels",
    "rename_to_arkit",
    "UNIT_IN_CM",
    "export_gltf",
    "export_animated_gltf",
    "find_gltf_validator",
    "validate_gltf",
    "head_rotation_quaternions",
    "morph_target_weights",
    "load_gltf_rig",
    "load_fbx_rig",
    "random_sparse_poses",
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
    "makehuman_quartic_rig",
    "overlapping_pairs",
    "remesh_rig",
    "save_rig",
    "synthesize_correctives",
]
