"""The blendshape rig of any corrective order, its (batched) evaluation, corrective synthesis,
the ict-quartic and MakeHuman quartic rigs, and rigs carried onto other meshes (remeshing,
deformation transfer).

Also importable here but not in ``__all__`` (for the other subpackages, the command line and
the avatar checks): ``CONTROL_SETS``, ``accessor_array``, ``add_morph_targets``,
``arkit_channels``, ``check_extra_sets``, ``check_humanoid``, ``combination_coefficients``,
``mesh_vertices``, ``node_descendants``, ``rename_to_arkit``, ``target_names``, and the glTF
avatar documents that ``autorig.auto_rig_avatar`` (``canrig autorig``) reads, rigs and
writes: ``GltfAvatar``, ``REQUIRED_BONES``, ``add_vrm_expressions``, ``avatar_from_fbx``,
``humanoid_bones``, ``read_gltf_avatar``, ``write_gltf_avatar``."""

from ._arkit import arkit_channels as arkit_channels
from ._arkit import rename_to_arkit as rename_to_arkit
from ._blendshape import UNIT_IN_CM, BlendshapeRig, Corrective, evaluate, evaluate_batch
from ._blendshape import combination_coefficients as combination_coefficients
from ._control_sets import CONTROL_SETS as CONTROL_SETS
from ._control_sets import control_set_of, select_control_set
from ._extras import EXTRA_SHAPES, with_extra_shapes
from ._extras import check_extra_sets as check_extra_sets
from ._fbx import load_fbx_rig
from ._gltf import export_gltf, load_gltf_rig
from ._gltf_animation import export_animated_gltf
from ._gltf_avatar import GltfAvatar as GltfAvatar
from ._gltf_avatar import accessor_array as accessor_array
from ._gltf_avatar import add_morph_targets as add_morph_targets
from ._gltf_avatar import avatar_from_fbx as avatar_from_fbx
from ._gltf_avatar import mesh_vertices as mesh_vertices
from ._gltf_avatar import node_descendants as node_descendants
from ._gltf_avatar import read_gltf_avatar as read_gltf_avatar
from ._gltf_avatar import target_names as target_names
from ._gltf_avatar import write_gltf_avatar as write_gltf_avatar
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
    synthesize_correctives,
)
from ._transfer import deformation_transfer, remesh_rig
from ._usd import export_usd, load_usd_rig
from ._vrm import REQUIRED_BONES as REQUIRED_BONES
from ._vrm import VRM_PRESETS
from ._vrm import add_vrm_expressions as add_vrm_expressions
from ._vrm import check_humanoid as check_humanoid
from ._vrm import humanoid_bones as humanoid_bones

__all__ = [
    "EXTRA_SHAPES",
    "MUTUALLY_EXCLUSIVE",
    "UNIT_IN_CM",
    "VRM_PRESETS",
    "BlendshapeRig",
    "Corrective",
    "SynthesisOptions",
    "SynthesisReport",
    "control_set_of",
    "deformation_gradient_blend",
    "deformation_transfer",
    "evaluate",
    "evaluate_batch",
    "exclusive_pairs",
    "export_animated_gltf",
    "export_gltf",
    "export_usd",
    "find_gltf_validator",
    "ict_linear_rig",
    "ict_quartic_rig",
    "load_fbx_rig",
    "load_gltf_rig",
    "load_rig",
    "load_usd_rig",
    "makehuman_quartic_rig",
    "random_sparse_poses",
    "remesh_rig",
    "save_rig",
    "select_control_set",
    "synthesize_correctives",
    "validate_gltf",
    "with_extra_shapes",
]
