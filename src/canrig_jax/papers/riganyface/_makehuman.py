"""The MakeHuman evaluation: every method on the MakeHuman hm08 head against its person-made
ARKit targets (evaluation only: nothing is fitted to them), and the per-shape record of the
rows (does the upper face move?)."""

import os
import time
from collections.abc import Mapping, Sequence

import numpy as np
from jaxtyping import ArrayLike, Float

from ...autorig._data import (
    AutorigDataset,
    copy_poses,
    face_placement,
    fit_head_landmarks,
    head_correspondence,
    transfer_poses,
)
from ...autorig._evaluation import (
    ACTIVE_MM,
    sculpted_shape_errors,
    sculpted_target_errors,
    shared_shape_matrix,
)
from ...autorig._makehuman import MakeHumanHead, load_makehuman
from ...autorig._model import RigAnyFace
from ._bases import anchored_base_key, generate_rows, transfer_bases
from ._heldout import UPPER_FACE

FACE_PLACED = " + face_placement"
"""Suffix of a MakeHuman row whose rig was generated with ``face_placement`` (the head placed
in the unit sphere from its fitted face) instead of the bounding box of the whole head: a
variant reported beside the protocol's rows."""


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


def makehuman_shapes(
    makehuman_example: tuple[
        MakeHumanHead,
        Float[ArrayLike, "S V 3"],
        Mapping[str, Float[ArrayLike, "S V 3"]],
        Sequence[str],
    ],
) -> dict:
    """Per shape on the MakeHuman head (``sculpted_shape_errors`` on its skin) of every row in
    ``evaluate_makehuman``'s example (head, (S, V, 3) targets, row -> (S, V, 3) predictions,
    S labels): {"labels", "target_peak_mm": (S,), "upper_face": (S,) bool (``UPPER_FACE``),
    "methods": row -> {"skin_mae_mm", "amplitude_ratio", "peak_mm", "peak_ratio"} (S,) each},
    as lists; the peak ratio is the row's largest vertex motion over the target's."""
    mh, truth, predictions, labels = makehuman_example
    if not predictions:
        raise ValueError("makehuman_example: expected at least one row of predictions, got none")
    methods, target_peak = {}, None
    for name, predicted in predictions.items():
        errors = sculpted_shape_errors(predicted, truth, mh.skin)
        target_peak = errors.pop("target_peak_mm")
        errors["peak_ratio"] = errors["peak_mm"] / target_peak
        methods[name] = {k: v.tolist() for k, v in errors.items()}
    return {
        "labels": [str(n) for n in labels],
        "target_peak_mm": np.asarray(target_peak).tolist(),
        "upper_face": [str(n).startswith(UPPER_FACE) for n in labels],
        "methods": methods,
    }
