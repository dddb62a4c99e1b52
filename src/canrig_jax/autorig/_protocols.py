"""Pieces of the auto-rigging evaluation protocols that are more than orchestration: the
deformation-transfer base of a training head kept on disk between runs, a head cut below the
chin as a face scan would be, and the name of the MakeHuman rows placed from the fitted face.

The experiment scripts (``experiments/autorig.py``) call these; the tests call them here.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float

from .._io import atomic_path
from ._data import AutorigDataset, RiggedHead, transfer_poses

FACE_PLACED = " + face_placement"
"""Suffix of a MakeHuman row whose rig was generated with ``face_placement`` (the head placed
in the unit sphere from its fitted face) instead of the bounding box of the whole head: a
variant reported beside the protocol's rows."""

CHIN_LANDMARK = 8
"""Multi-PIE index of the chin among ICT's 68 landmarks."""


def cached_transfer(
    dataset: AutorigDataset,
    head: RiggedHead,
    cache: str | Path | None,
    seed: int,
    static_below: float | None = None,
    *,
    anchor: str = "vertex",
) -> Float[np.ndarray, "P V 3"]:
    """``transfer_poses(dataset, head, static_below=, anchor=)`` as float32 (cm), kept in the
    folder ``cache`` when it is given (``None``: always computed).

    The file is named by the kind of transfer (plain, or anchored below ``static_below`` cm per
    ``anchor``), ``seed`` (the training set's) and ``head.name``; a stored array is used only
    if its shape is ``head.displacements``' (P, V, 3), else it is recomputed and replaced
    (written atomically)."""
    path = None
    if cache is not None:
        kind = "dt" if static_below is None else f"dt_anchored{static_below:g}"
        kind += "" if static_below is None or anchor == "vertex" else f"_{anchor}"
        path = Path(cache) / f"{kind}_seed{seed}_{head.name.replace('/', '_')}.npy"
        if path.exists():
            stored = np.load(path, allow_pickle=False)
            if stored.shape == head.displacements.shape:
                return stored
    transferred = transfer_poses(dataset, head, static_below=static_below, anchor=anchor)
    transferred = transferred.astype(np.float32)
    if path is not None:
        with atomic_path(path) as tmp, open(tmp, "wb") as file:
            np.save(file, transferred, allow_pickle=False)
    return transferred


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
