"""Pieces of the auto-rigging evaluation protocols that are more than orchestration: the
deformation-transfer bases of a head (kept on disk between runs for the training heads), each
evaluated method's rig on a head, the MakeHuman evaluation against its person-made ARKit
targets, and a head cut below the chin as a face scan would be.

The experiment scripts (``experiments/autorig.py``) call these; the tests call them here.
"""

import dataclasses
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int, Int32

from .._io import atomic_path
from ..mesh import MeshOperators, TriangleCorrespondence
from ._data import (
    AutorigDataset,
    PoseSet,
    RiggedHead,
    copy_poses,
    face_placement,
    fit_head_landmarks,
    head_correspondence,
    transfer_poses,
)
from ._evaluation import ACTIVE_MM, sculpted_target_errors, shared_shape_matrix
from ._makehuman import MakeHumanHead, load_makehuman
from ._methods import ANCHOR_CM
from ._model import RigAnyFace
from ._rig import GeneratedRig, generate_rig

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


def anchored_base_key(mode: str) -> str:
    """Key of the deformation-transfer base anchored per ``mode`` (``transfer_poses(anchor=)``)
    in ``transfer_bases``' result, and its rows' suffix without the leading '_': "anchored"
    for "vertex", "anchored_<mode>" else."""
    return "anchored" if mode == "vertex" else f"anchored_{mode}"


def transfer_bases(
    dataset: AutorigDataset,
    head: RiggedHead | MakeHumanHead,
    correspondence: TriangleCorrespondence | None = None,
    plain: Float[np.ndarray, "P V 3"] | None = None,
    anchors: Sequence[str] = ("vertex",),
) -> dict[str, Float[np.ndarray, "P V 3"]]:
    """The residual models' bases on ``head`` (cm): ``"plain"``, deformation transfer of every
    pose (``plain`` when already computed), and the transfer anchored below
    ``ANCHOR_CM`` per each mode of ``anchors``, under ``anchored_base_key(mode)``."""
    if plain is None:
        plain = transfer_poses(dataset, head, correspondence)
    bases = {"plain": plain}
    for mode in anchors:
        bases[anchored_base_key(mode)] = transfer_poses(
            dataset, head, correspondence, static_below=ANCHOR_CM, anchor=mode
        )
    return bases


def generate_rows(
    models: Mapping[str, RigAnyFace],
    rows: Mapping[str, tuple[str, str | None]],
    poses: PoseSet,
    head: RiggedHead | MakeHumanHead,
    bases: Mapping[str, Float[ArrayLike, "P V 3"]],
    operators: MeshOperators | None = None,
    placement: tuple[Float[ArrayLike, " 3"], float] | None = None,
) -> dict[str, GeneratedRig]:
    """Each evaluation row's rig generated on ``head`` (``head.vertices`` (V, 3) cm,
    ``head.faces``): ``rows`` maps a row name to (a name in ``models``, the key of its base in
    ``bases`` or None for a model without one); ``operators`` and ``placement`` are
    ``generate_rig``'s (default: computed, and the head's bounding box)."""
    return {
        name: generate_rig(
            models[model_name],
            poses,
            head.vertices,
            head.faces,
            operators=operators,
            base=None if base is None else bases[base],
            placement=placement,
        )
        for name, (model_name, base) in rows.items()
    }


def evaluate_makehuman(
    dataset: AutorigDataset,
    models: Mapping[str, RigAnyFace],
    rows: Mapping[str, tuple[str, str | None]],
    data_dir: str | os.PathLike | None = None,
    anchors: Sequence[str] = ("vertex",),
    face_placed: bool = False,
) -> tuple[
    dict,
    dict,
    tuple[
        MakeHumanHead,
        Float[np.ndarray, "S V 3"],
        dict[str, Float[np.ndarray, "S V 3"]],
        list[str],
    ],
]:
    """Every method on the MakeHuman hm08 head against its person-made ARKit targets, over the
    shapes it shares with ICT (evaluation only: nothing is fitted to the targets).

    The ICT face part is fitted to the head (``fit_head_landmarks``: trimmed-ICP similarity,
    ICT's 68 landmarks snapped to the skin), the correspondence built from those landmarks
    (``head_correspondence``); the rows are no motion, copied ICT deltas, deformation transfer
    (plain, and anchored per each mode of ``anchors``), and ``rows`` (see ``generate_rows``)
    of ``models``; with ``face_placed``, each model row once more with ``face_placement``
    (rows suffixed ``FACE_PLACED``). Each row's single-expression poses are mapped to
    MakeHuman's shapes (``shared_shape_matrix``) and compared on the skin
    (``sculpted_target_errors``).

    Returns (row -> errors in mm and the amplitude ratio, the protocol's record, and
    (the head, (S, V, 3) target deltas in cm, row -> (S, V, 3) predictions without no motion,
    the S shape names) for figures)."""
    mh = load_makehuman(data_dir)
    poses = dataset.poses
    start = time.perf_counter()
    landmarks, fit = fit_head_landmarks(dataset, mh.neutral, mh.faces, region=mh.skin)
    correspondence = head_correspondence(dataset, mh.neutral, mh.faces, landmarks)
    seconds_correspondence = time.perf_counter() - start
    start = time.perf_counter()
    transferred = transfer_poses(dataset, mh, correspondence)
    seconds_transfer = time.perf_counter() - start
    bases = transfer_bases(dataset, mh, correspondence, plain=transferred, anchors=anchors)
    predictions = {
        "no_motion": np.zeros_like(transferred),
        "copy_deltas": copy_poses(dataset, mh, correspondence),
        "deformation_transfer": transferred,
    }
    for mode in anchors:
        key = anchored_base_key(mode)
        predictions["deformation_transfer_" + key] = bases[key]
    for name, generated in generate_rows(models, rows, poses, mh, bases).items():
        predictions[name] = generated.displacements
    if face_placed:
        placement = face_placement(dataset, mh.neutral, mh.faces, fit=fit)
        placed = generate_rows(models, rows, poses, mh, bases, placement=placement)
        for name, generated in placed.items():
            predictions[name + FACE_PLACED] = generated.displacements
    target_index, matrix = shared_shape_matrix(poses.basis_names, mh.names)
    truth = mh.deltas[target_index]
    singles = {
        name: np.einsum("sk,kvd->svd", matrix, p[: poses.n_basis])
        for name, p in predictions.items()
    }
    results = {name: sculpted_target_errors(p, truth, mh.skin) for name, p in singles.items()}
    # which ICT part each MakeHuman component was matched to (majority of its vertices)
    source_face = correspondence.vertex_map.triangle
    source_part = np.searchsorted(
        dataset.head.part_vertex_range[:, 1], dataset.head.faces[source_face, 0], side="right"
    )
    matched = {}
    for label in np.unique(mh.component_labels):
        parts = source_part[mh.component_labels == label]
        matched[f"component_{int(label)} ({int(np.sum(mh.component_labels == label))} v)"] = str(
            dataset.head.part_names[np.bincount(parts).argmax()]
        )
    info = {
        "vertices": int(mh.neutral.shape[0]),
        "shared_shapes": len(target_index),
        "units": "decimetres x 10 -> cm",
        "alignment": "trimmed-ICP similarity of the ICT face part (90 % of pairs kept; start: "
        "identity rotation, nose tips together), ICT's 68 landmarks snapped to the skin",
        "fit_scale": fit.scale,
        "fit_trimmed_rms_cm": fit.rms,
        "fit_iterations": fit.iterations,
        "matched_parts": matched,
        "skin": "largest component",
        "active_mm": ACTIVE_MM,
        "seconds_landmarks_and_correspondence": seconds_correspondence,
        "seconds_deformation_transfer": seconds_transfer,
    }
    labels = [mh.names[i] for i in target_index]
    example = (mh, truth, {k: v for k, v in singles.items() if k != "no_motion"}, labels)
    return results, info, example
