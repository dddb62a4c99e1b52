"""Loaders for the real assets in the shared data folder (ICT, Live Link Face, MediaPipe)."""

from ._fbx import FbxMesh, FbxScene, FbxSkin, load_fbx, load_fbx_meshes, load_fbx_scene
from ._head_file import (
    HEAD_FORMATS,
    HEAD_PLAUSIBLE_CM,
    HEAD_SIZE_CM,
    HEAD_UNITS_CM,
    HeadMesh,
    infer_units,
    load_head,
    save_obj,
)
from ._ict import (
    ENCLOSING_PARTS,
    FACE,
    ICT_PARTS,
    INNER_PARTS,
    ICTFaceModel,
    ict_identity,
    load_ict,
    load_ict_obj_folder,
    load_identity_modes,
)
from ._livelink_csv import (
    LIVELINK_CSV_CHANNELS,
    LIVELINK_ROTATIONS,
    capture_from_weights,
    format_timecode,
    parse_timecode,
    read_livelink_csv,
    write_livelink_csv,
)
from ._livelinkface import LiveLinkCapture, load_livelinkface
from ._mediapipe import MediaPipeFace, load_mediapipe_face
from ._names import ARKIT_NAMES, RetargetReport, arkit_name_of, retarget_weights, to_arkit
from ._paths import ENV_VAR, data_file, read_arrays, resolve_data_dir

__all__ = [
    "FbxMesh",
    "FbxScene",
    "FbxSkin",
    "load_fbx_scene",
    "load_fbx",
    "load_fbx_meshes",
    "arkit_name_of",
    "HEAD_FORMATS",
    "HEAD_PLAUSIBLE_CM",
    "HEAD_SIZE_CM",
    "HEAD_UNITS_CM",
    "HeadMesh",
    "infer_units",
    "load_head",
    "save_obj",
    "LIVELINK_CSV_CHANNELS",
    "LIVELINK_ROTATIONS",
    "capture_from_weights",
    "format_timecode",
    "parse_timecode",
    "read_livelink_csv",
    "write_livelink_csv",
    "data_file",
    "read_arrays",
    "ARKIT_NAMES",
    "ENCLOSING_PARTS",
    "ENV_VAR",
    "FACE",
    "ICT_PARTS",
    "ICTFaceModel",
    "INNER_PARTS",
    "LiveLinkCapture",
    "MediaPipeFace",
    "RetargetReport",
    "ict_identity",
    "load_ict",
    "load_ict_obj_folder",
    "load_identity_modes",
    "load_livelinkface",
    "load_mediapipe_face",
    "resolve_data_dir",
    "retarget_weights",
    "to_arkit",
]
