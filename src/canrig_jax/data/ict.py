"""ICT Face Model (USC ICT, MIT licence): neutral head, 53 ARKit-named expressions,
100 identity modes, 17 parts. Units are centimetres.

``load_ict`` reads the ``.npz`` extraction in ``ict-facekit/``; ``load_ict_obj_folder``
reads ICT-FaceKit's original folder format (one OBJ per shape plus
``vertex_indices.json``). ``ICTFaceModel.select`` restricts the model to parts.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np

from .paths import data_file

FACE = ("Face",)
"""The face part alone: vertices 0..9408 (9,409 vertices)."""


@dataclasses.dataclass(frozen=True)
class ICTFaceModel:
    """The ICT Face Model (or a part selection of it) as host NumPy arrays, centimetres.

    Attributes:
        neutral: (V, 3) float32 neutral head.
        faces: (F, 3) int32 triangles indexing ``neutral``.
        deltas: (K, V, 3) float32 expression offsets from the neutral.
        names: K expression names (ICT's ARKit spelling, ``eyeBlink_L``).
        part_names: names of the parts kept, in vertex order.
        part_vertex_range: (P, 2) half-open vertex range of each kept part.
        component_labels: (V,) connected component of each vertex (original labels).
        landmarks: (L,) Multi-PIE-68 landmark vertices; -1 where the selection dropped one.
        vertex_ids: (V,) index of each vertex in the full 26,719-vertex head.
    """

    neutral: np.ndarray
    faces: np.ndarray
    deltas: np.ndarray
    names: tuple[str, ...]
    part_names: tuple[str, ...]
    part_vertex_range: np.ndarray
    component_labels: np.ndarray
    landmarks: np.ndarray
    vertex_ids: np.ndarray

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    def select(self, parts: Sequence[str] | str | None = FACE) -> ICTFaceModel:
        """Restrict to a list of part names (``None`` or ``"head"`` keeps all 17 parts).

        Faces are kept when all three corners are kept, and re-indexed.
        """
        if parts is None or parts == "head":
            return self
        if isinstance(parts, str):
            parts = (parts,)
        unknown = [p for p in parts if p not in self.part_names]
        if unknown:
            raise ValueError(
                f"parts: unknown part name(s) {unknown}; known parts are {list(self.part_names)}"
            )
        order = [i for i, name in enumerate(self.part_names) if name in set(parts)]
        keep = np.concatenate(
            [np.arange(*self.part_vertex_range[i]) for i in order]
        ).astype(np.int64)
        new_index = np.full(self.n_vertices, -1, dtype=np.int64)
        new_index[keep] = np.arange(keep.size)
        face_kept = np.all(new_index[self.faces] >= 0, axis=1)
        sizes = np.diff(self.part_vertex_range[order], axis=1)[:, 0]
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        landmarks = np.where(self.landmarks >= 0, new_index[self.landmarks], -1)
        return ICTFaceModel(
            neutral=self.neutral[keep],
            faces=new_index[self.faces[face_kept]].astype(np.int32),
            deltas=self.deltas[:, keep],
            names=self.names,
            part_names=tuple(self.part_names[i] for i in order),
            part_vertex_range=np.stack([starts, starts + sizes], axis=1).astype(np.int32),
            component_labels=self.component_labels[keep],
            landmarks=landmarks.astype(np.int32),
            vertex_ids=self.vertex_ids[keep],
        )


def load_ict(
    data_dir: str | os.PathLike | None = None, parts: Sequence[str] | str | None = None
) -> ICTFaceModel:
    """Load the ICT Face Model from ``ict-facekit/expressions.npz``.

    Args:
        data_dir: data folder (else ``$CANRIG_DATA``, else ``../shared/data``).
        parts: part names to keep (``FACE`` for the 9,409-vertex face); ``None`` keeps
            the whole 26,719-vertex head.
    """
    with np.load(data_file("ict-facekit/expressions.npz", data_dir), allow_pickle=False) as z:
        model = ICTFaceModel(
            neutral=z["neutral"].astype(np.float32),
            faces=z["faces"].astype(np.int32),
            deltas=z["deltas"].astype(np.float32),
            names=tuple(str(n) for n in z["names"]),
            part_names=tuple(str(n) for n in z["part_names"]),
            part_vertex_range=z["part_vertex_range"].astype(np.int32),
            component_labels=z["component_labels"].astype(np.int32),
            landmarks=z["landmarks_multipie68"].astype(np.int32),
            vertex_ids=np.arange(z["neutral"].shape[0], dtype=np.int32),
        )
    return model.select(parts)


def load_identity_modes(data_dir: str | os.PathLike | None = None) -> np.ndarray:
    """The (100, 26719, 3) float32 identity PCA modes, offsets from the neutral (cm)."""
    with np.load(data_file("ict-facekit/identity.npz", data_dir), allow_pickle=False) as z:
        return z["identity_deltas"].astype(np.float32)


def ict_identity(
    coefficients: np.ndarray,
    data_dir: str | os.PathLike | None = None,
    model: ICTFaceModel | None = None,
) -> np.ndarray:
    """Neutral head of an identity: neutral + sum_i c_i mode_i (cm).

    Args:
        coefficients: (n,) with n <= 100, weights of the first n identity modes, drawn
            from a standard normal in the kit's own ``randomize_identity``.
        model: a (possibly part-selected) model whose vertices to return; default whole head.

    Returns:
        (V, 3) float32 neutral vertices of that identity, V as in ``model``.
    """
    coefficients = np.asarray(coefficients, dtype=np.float64)
    if coefficients.ndim != 1 or not 1 <= coefficients.size <= 100:
        raise ValueError(
            f"coefficients: expected a 1-D array of 1 to 100 identity weights, "
            f"got shape {coefficients.shape}"
        )
    if not np.all(np.isfinite(coefficients)):
        raise ValueError("coefficients: contains non-finite values")
    model = load_ict(data_dir) if model is None else model
    modes = load_identity_modes(data_dir)[: coefficients.size][:, model.vertex_ids]
    offset = np.tensordot(coefficients, modes, axes=1)
    return (model.neutral + offset).astype(np.float32)
