"""Heads cut as scans and masks would be: below the chin (a face scan) and to the front of
the face (a face-only mask). Centimetres, +y up, facing +z."""

import dataclasses

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int, Int32

from ...autorig._data import RiggedHead

CHIN_LANDMARK = 8
"""Multi-PIE index of the chin among ICT's 68 landmarks."""


def crop_below_chin(
    head: RiggedHead, margin_cm: float = 1.0
) -> tuple[RiggedHead, Bool[np.ndarray, " V"]]:
    """``head`` without the triangles reaching lower (y, cm) than its chin landmark (Multi-PIE
    8) minus ``margin_cm``: a head cut as a face scan would be.

    Returns the cut head (named ``<name>/cut_below_chin``; its vertices, faces, displacements,
    landmarks and parts re-indexed to the kept vertices) and the (V,) bool mask of the kept
    vertices (those of a kept triangle). ``margin_cm`` > 0."""
    if not margin_cm > 0:
        raise ValueError(f"margin_cm: expected > 0 cm (the chin itself is kept), got {margin_cm}")
    chin = float(head.vertices[head.landmarks[CHIN_LANDMARK], 1])
    keep_faces = (head.vertices[head.faces][:, :, 1] > chin - margin_cm).all(axis=1)
    kept = np.zeros(head.n_vertices, bool)
    kept[head.faces[keep_faces]] = True
    index = np.cumsum(kept) - 1
    cut = dataclasses.replace(
        head,
        name=head.name + "/cut_below_chin",
        vertices=head.vertices[kept],
        faces=index[head.faces[keep_faces]].astype(np.int32),
        displacements=head.displacements[:, kept],
        landmarks=index[head.landmarks],
        parts=head.parts[kept],
    )
    return cut, kept


def face_crop(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> tuple[Float[np.ndarray, "Vc 3"], Int32[np.ndarray, "Fc 3"]]:
    """The front of a head (cm, +y up, facing +z), as a face-only mask would be: the vertices
    within the front 45 % of its depth and between 10 % and 75 % of its height from the top,
    the triangles wholly inside. Returns ((Vc, 3) vertices, (Fc, 3) int32 triangles
    re-indexed to them)."""
    v = np.asarray(vertices)
    faces = np.asarray(faces)
    depth, height = np.ptp(v[:, 2]), np.ptp(v[:, 1])
    keep = (v[:, 2] > v[:, 2].max() - 0.45 * depth) & (v[:, 1] > v[:, 1].max() - 0.75 * height)
    keep &= v[:, 1] < v[:, 1].max() - 0.1 * height
    inside = keep[faces].all(axis=1)
    used = np.zeros(len(v), bool)
    used[faces[inside].ravel()] = True
    index = np.cumsum(used) - 1
    return v[used], index[faces[inside]].astype(np.int32)
