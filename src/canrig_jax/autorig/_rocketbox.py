"""The two Microsoft Rocketbox heads of the data folder (MIT) with their artists' 52 ARKit
shapes: heads sculpted by other people, to check a rig against (``rocketbox/<name>_head.npz``,
cropped from the avatars as ``rocketbox/rocketbox.json`` records). Centimetres, +y up, facing
+z."""

import os
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float, Float32, Int

from ..data import data_file, read_arrays
from ._landmarks import skin_of


class SculptedHead:
    """A head with its artist's ARKit shapes: ``vertices`` (V, 3) and ``deltas`` (S, V, 3) in
    cm (+y up, facing +z), ``faces`` (F, 3), the S ``names``, and ``skin``: (V,) its largest
    component (``skin_of``)."""

    def __init__(
        self,
        name: str,
        vertices: Float[ArrayLike, "V 3"],
        faces: Int[ArrayLike, "F 3"],
        deltas: Float[ArrayLike, "S V 3"],
        names: Sequence[str],
    ):
        self.name = name
        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int32)
        self.deltas = np.asarray(deltas, np.float32)
        self.names = [str(n) for n in names]
        if self.deltas.shape != (len(self.names), *self.vertices.shape):
            raise ValueError(
                f"deltas: expected ({len(self.names)}, {len(self.vertices)}, 3) for the names "
                f"and vertices, got {self.deltas.shape}"
            )
        self.skin = skin_of(self.vertices, self.faces)

    def shapes(self, names: Sequence[str]) -> Float32[np.ndarray, "n V 3"]:
        """(len(names), V, 3) the artist's shapes of ``names``, cm."""
        return np.stack([self.deltas[self.names.index(n)] for n in names])


def load_rocketbox_head(name: str, data_dir: str | os.PathLike | None = None) -> SculptedHead:
    """A Rocketbox head (``rocketbox/<name>_head.npz`` in the data folder: ``"Male_Adult_08"``
    or ``"Female_Adult_01"``) with its artist's ARKit shapes, as a ``SculptedHead``
    (``vertices``, ``faces``, ``deltas`` and ``names`` of the shapes, ``skin``), in cm."""
    path = data_file(f"rocketbox/{name}_head.npz", data_dir)
    z = read_arrays(path, ("neutral", "faces", "deltas", "names"))
    names = [str(n) for n in z["names"]]
    return SculptedHead(name, z["neutral"], z["faces"], z["deltas"], names)
