"""Loaders for the real assets in the shared data folder (ICT, Live Link Face, MediaPipe).

Also importable here but not in ``__all__`` (for the other subpackages and the command line):
``ENCLOSING_PARTS``, ``FbxScene``, ``INNER_PARTS``, ``HEAD_PLAUSIBLE_CM``,
``capture_from_weights``, ``format_timecode``."""

from ._fbx import FbxScene as FbxScene
from ._fbx import load_fbx, load_fbx_scene
from ._head_file import HEAD_PLAUSIBLE_CM as HEAD_PLAUSIBLE_CM
from ._head_file import load_head, save_obj
from ._ict import ENCLOSING_PARTS as ENCLOSING_PARTS
from ._ict import FACE, ICTFaceModel, ict_identity, load_ict, load_ict_obj_folder
from ._ict import INNER_PARTS as INNER_PARTS
from ._livelink_csv import LIVELINK_CSV_CHANNELS, read_livelink_csv, write_livelink_csv
from ._livelink_csv import capture_from_weights as capture_from_weights
from ._livelink_csv import format_timecode as format_timecode
from ._livelinkface import LiveLinkCapture, load_livelinkface
from ._mediapipe import load_mediapipe_face
from ._names import ARKIT_NAMES, arkit_name_of, retarget_weights, to_arkit
from ._paths import data_file, read_arrays

__all__ = [
    "ARKIT_NAMES",
    "FACE",
    "LIVELINK_CSV_CHANNELS",
    "ICTFaceModel",
    "LiveLinkCapture",
    "arkit_name_of",
    "data_file",
    "ict_identity",
    "load_fbx",
    "load_fbx_scene",
    "load_head",
    "load_ict",
    "load_ict_obj_folder",
    "load_livelinkface",
    "load_mediapipe_face",
    "read_arrays",
    "read_livelink_csv",
    "retarget_weights",
    "save_obj",
    "to_arkit",
    "write_livelink_csv",
]
