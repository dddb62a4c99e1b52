"""Loaders for the real assets in the shared data folder (ICT, Live Link Face, MediaPipe)."""

from .ict import FACE, ICTFaceModel, ict_identity, load_ict, load_identity_modes
from .paths import ENV_VAR, resolve_data_dir

__all__ = [
    "ENV_VAR",
    "FACE",
    "ICTFaceModel",
    "ict_identity",
    "load_ict",
    "load_identity_modes",
    "resolve_data_dir",
]
