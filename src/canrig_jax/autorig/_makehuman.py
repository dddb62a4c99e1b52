"""The MakeHuman hm08 head (CC0) with its 52 person-made ARKit targets (MIT): a head of
another topology, made by other people than ICT's. **For evaluation only**: nothing may be
trained or tuned on it. Stored in MakeHuman decimetres; ``load_makehuman`` returns
centimetres (like ICT)."""

import dataclasses
import os

import numpy as np
from jaxtyping import Bool, Float32, Int, Int32

from ..data import data_file, read_arrays

DM_TO_CM = 10.0


@dataclasses.dataclass(frozen=True)
class MakeHumanHead:
    """The hm08 head crop in centimetres.

    Attributes:
        neutral: (4920, 3) float32 vertices, cm (y up, facing +z).
        faces: (9684, 3) int32 triangles (the stored quads fan-split).
        deltas: (52, 4920, 3) float32 ARKit targets, cm; names: their ARKit names.
        component_labels: (4920,) connected component of each vertex (0: the skin).
    """

    neutral: Float32[np.ndarray, "V 3"]
    faces: Int32[np.ndarray, "F 3"]
    deltas: Float32[np.ndarray, "K V 3"]
    names: tuple[str, ...]
    component_labels: Int[np.ndarray, " V"]

    @property
    def vertices(self) -> Float32[np.ndarray, "V 3"]:
        """The neutral (the name ``transfer_poses`` and ``copy_poses`` read)."""
        return self.neutral

    @property
    def skin(self) -> Bool[np.ndarray, " V"]:
        """(V,) bool: the vertices of the largest component (the skin; the others are eye,
        teeth and tongue proxies)."""
        labels = self.component_labels
        return labels == np.argmax(np.bincount(labels))


def load_makehuman(data_dir: str | os.PathLike | None = None) -> MakeHumanHead:
    """Load ``makehuman/hm08_face.npz``: the 52 ARKit targets (not the visemes), in cm, as a
    ``MakeHumanHead`` (``neutral``, ``faces``, ``deltas`` and ``names`` of the targets,
    ``component_labels``, ``skin``)."""
    path = data_file("makehuman/hm08_face.npz", data_dir)
    z = read_arrays(path, ("neutral", "faces", "deltas", "names", "component_labels"))
    names = [str(n) for n in z["names"]]
    arkit = [i for i, n in enumerate(names) if not n.startswith("viseme_")]
    return MakeHumanHead(
        neutral=(z["neutral"] * DM_TO_CM).astype(np.float32),
        faces=z["faces"].astype(np.int32),
        deltas=(z["deltas"][arkit] * DM_TO_CM).astype(np.float32),
        names=tuple(names[i] for i in arkit),
        component_labels=z["component_labels"].astype(np.int32),
    )
