"""MediaPipe's canonical face model (Apache-2.0): a 468-vertex neutral face surface with
UVs and no blendshapes, in centimetres; a different topology from ICT."""

import dataclasses
import os

import numpy as np
from jaxtyping import Float32, Int32

from ._paths import data_file, read_arrays


@dataclasses.dataclass(frozen=True)
class MediaPipeFace:
    """The canonical face as host NumPy arrays (``load_mediapipe_face`` lists the fields)."""

    neutral: Float32[np.ndarray, "V 3"]
    faces: Int32[np.ndarray, "F 3"]
    uv: Float32[np.ndarray, "U 2"]
    face_uv_idx: Int32[np.ndarray, "F 3"]


def load_mediapipe_face(data_dir: str | os.PathLike | None = None) -> MediaPipeFace:
    """Load ``mediapipe/canonical_face.npz``.

    Args:
        data_dir: data folder (else ``$CANRIG_DATA``, else ``../shared/data``).

    Returns:
        The canonical face as host NumPy arrays (a ``MediaPipeFace``): ``neutral`` (468, 3)
        float32 vertex positions, cm; ``faces`` (898, 3) int32 triangles indexing
        ``neutral``; ``uv`` (468, 2) float32 texture coordinates; ``face_uv_idx`` (898, 3)
        int32 triangles indexing ``uv``.
    """
    path = data_file("mediapipe/canonical_face.npz", data_dir)
    z = read_arrays(path, ("neutral", "faces", "uv", "face_uv_idx"))
    return MediaPipeFace(
        neutral=z["neutral"].astype(np.float32),
        faces=z["faces"].astype(np.int32),
        uv=z["uv"].astype(np.float32),
        face_uv_idx=z["face_uv_idx"].astype(np.int32),
    )
