"""The auto-rigging experiments' evaluation on held-out ICT identities: which rows a set of
models is evaluated as, every row's predictions on the held-out heads (the standard run's two
splits, or the unseen-topology heads alone for checkpoints evaluated apart), the per-shape
record (does the upper face move?), penetration where the ground truth has none, and
placement by the bounding box against placement from the face.

Displacements are in centimetres, (P, V, 3) per head (P poses of ``dataset.poses``); errors in
millimetres. The scripts ``experiments/autorig*.py`` call these.
"""

import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ...autorig._data import (
    AutorigDataset,
    PoseSet,
    RiggedHead,
    copy_poses,
    face_placement,
    head_correspondence,
)
from ...autorig._evaluation import sculpted_shape_errors
from ...autorig._metrics import error_stats, inner_outside, penetration, penetration_free_set
from ...autorig._model import RigAnyFace, normalise
from ...autorig._rig import generate_rig
from ...autorig._train import head_inputs, load_riganyface
from ...mesh import MeshOperators
from ._bases import anchored_base_key, generate_rows, transfer_bases
from ._crops import crop_below_chin
from ._recipes import ANCHORED_RESIDUAL_MODELS

SPLITS = ("same_topology", "unseen_topology")
"""The held-out splits of ``ict_autorig_dataset``: new identities on a training remeshing, and
on a resolution never trained on."""


HELDOUT_SPLIT = "unseen_topology"
"""The split the per-class, per-shape, penetration and placement protocols use."""


ANCHORED_ROW = "_anchored"
"""Suffix of a residual model's row evaluated on anchored deformation transfer (trained on
plain): ``raf_dt_residual_anchored``."""


UPPER_FACE = ("brow", "eye", "cheekSquint")
"""ARKit shapes of the upper face (name prefixes), for the per-region summaries."""


def evaluation_rows(models: Mapping[str, RigAnyFace]) -> dict[str, tuple[str, str | None]]:
    """Row name -> (model name, its base: None, "plain" or an anchored base's key) of each
    model: a pure model once without a base; a residual model trained on anchored deformation
    transfer (``ANCHORED_RESIDUAL_MODELS``) once on its own base; any other residual model on
    plain deformation transfer (as trained) and once more on the per-vertex anchored one
    (row suffixed ``ANCHORED_ROW``)."""
    rows: dict[str, tuple[str, str | None]] = {}
    for name, model in models.items():
        if not model.residual:
            rows[name] = (name, None)
        elif name in ANCHORED_RESIDUAL_MODELS:
            rows[name] = (name, anchored_base_key(ANCHORED_RESIDUAL_MODELS[name]))
        else:
            rows[name] = (name, "plain")
            rows[name + ANCHORED_ROW] = (name, "anchored")
    return rows


def load_checkpoint_rows(paths: Sequence[str | Path]) -> dict[str, tuple[RigAnyFace, dict]]:
    """Row name ``"<folder>/<file stem>"`` -> (model, header) of each RigAnyFace checkpoint
    in ``paths`` (``load_riganyface``); a missing file is a ``ValueError`` naming it, before
    any is loaded."""
    paths = [Path(p) for p in paths]
    for path in paths:
        if not path.is_file():
            raise ValueError(f"paths: no checkpoint {path}")
    models = {}
    for path in paths:
        model, _, header = load_riganyface(path)
        models[f"{path.parent.name}/{path.stem}"] = model, header
    return models


def head_predictions(
    dataset: AutorigDataset,
    head: RiggedHead,
    models: Mapping[str, RigAnyFace],
    rows: Mapping[str, tuple[str, str | None]],
    anchors: Sequence[str] = ("vertex",),
    *,
    copy: bool = True,
    operators: MeshOperators | None = None,
) -> dict[str, Float[np.ndarray, "P V 3"]]:
    """Row -> (P, V, 3) predicted displacements (cm) on one held-out ``head``: copied ICT
    deltas (``copy``), deformation transfer plain and anchored per each mode of ``anchors``
    (rows ``deformation_transfer`` and ``deformation_transfer_<key>``), and each of ``rows``
    (``generate_rows``; ``operators``: the head's, when already computed). The correspondence
    is ``head_correspondence`` from the head's landmarks."""
    correspondence = head_correspondence(dataset, head.vertices, head.faces, head.landmarks)
    bases = transfer_bases(dataset, head, correspondence, anchors=tuple(anchors))
    predicted = {}
    if copy:
        predicted["copy_deltas"] = copy_poses(dataset, head, correspondence)
    predicted["deformation_transfer"] = bases["plain"]
    for mode in anchors:
        key = anchored_base_key(mode)
        predicted["deformation_transfer_" + key] = bases[key]
    generated = generate_rows(models, rows, dataset.poses, head, bases, operators=operators)
    predicted.update({name: rig.displacements for name, rig in generated.items()})
    return predicted


def heldout_predictions(
    dataset: AutorigDataset,
    models: Mapping[str, RigAnyFace],
    anchors: Sequence[str] = ("vertex",),
    *,
    copy: bool = False,
    rows: Mapping[str, tuple[str, str | None]] | None = None,
) -> tuple[dict[str, list[Float[np.ndarray, "P _V 3"]]], list[Float[np.ndarray, "P _V 3"]]]:
    """Every ``HELDOUT_SPLIT`` head of ``dataset``: (row -> (P, V, 3) predictions per head,
    (P, V, 3) ground truth per head), cm. Rows: no motion, copied ICT deltas (``copy``),
    deformation transfer plain and anchored per each mode of ``anchors``, and ``rows``
    (default: each model, a residual one on plain DT under its name and on each anchored base
    as ``"<name>+<key>_base"``)."""
    if rows is None:
        rows = {}
        for name, model in models.items():
            keys = ("plain", *map(anchored_base_key, anchors)) if model.residual else (None,)
            for base in keys:
                rows[name if base in (None, "plain") else f"{name}+{base}_base"] = (name, base)
    predicted: dict[str, list[Float[np.ndarray, "P _V 3"]]] = {"no_motion": []}
    truth = []
    for head in dataset.test[HELDOUT_SPLIT]:
        truth.append(head.displacements)
        predicted["no_motion"].append(np.zeros_like(head.displacements))
        for name, p in head_predictions(dataset, head, models, rows, anchors, copy=copy).items():
            predicted.setdefault(name, []).append(p)
        print(f"predicted {head.name}")
    return predicted, truth


def split_errors(
    predicted: Sequence[Float[ArrayLike, "P _V 3"]],
    truth: Sequence[Float[ArrayLike, "P _V 3"]],
    scales: Sequence[float],
) -> dict:
    """One row's errors over the heads of a split (``error_stats`` of the (P, V, 3) arrays
    per head, cm -> mm), with the MAE and q95 on the heads normalised to the unit sphere
    (each head's arrays divided by its ``normalise`` scale ``scales``, cm), x 1000, and the
    number of heads."""
    stats = error_stats(np.concatenate(predicted, 1), np.concatenate(truth, 1))
    unit = error_stats(
        np.concatenate([p / s for p, s in zip(predicted, scales, strict=True)], 1),
        np.concatenate([t / s for t, s in zip(truth, scales, strict=True)], 1),
        scale=100.0,  # unit-sphere units x 1000 (error_stats multiplies by CM_TO_MM)
    )
    return {
        **stats,
        "mae_unit_sphere_x1000": unit["mae_mm"],
        "q95_unit_sphere_x1000": unit["q95_mm"],
        "heads": len(predicted),
    }


def evaluate_splits(
    dataset: AutorigDataset,
    models: Mapping[str, RigAnyFace],
    rows: Mapping[str, tuple[str, str | None]],
    anchors: Sequence[str] = ("vertex",),
    *,
    k: int = 128,
) -> dict:
    """The standard run's held-out evaluation on both ``SPLITS``: copied deltas, deformation
    transfer (plain and anchored per ``anchors``) and ``rows`` of ``models`` on every head
    (``head_predictions``, the head's operators with ``k`` eigenvectors).

    Returns {"test": row -> split -> ``split_errors``, "penetration": row and
    ``"ground_truth"`` -> mean ``penetration`` over the heads of both splits (rows of
    ``rows`` only), "examples": split -> (its first head, row -> that head's predictions),
    "predictions": row -> (P, V, 3) per ``HELDOUT_SPLIT`` head (``no_motion`` first), "truth":
    the (P, V, 3) ground truth per such head}."""
    part_names = dataset.head.part_names
    test: dict[str, dict] = {}
    pen: dict[str, list[float]] = {name: [] for name in (*rows, "ground_truth")}
    out: dict = {"examples": {}}
    for split in SPLITS:
        predicted: dict[str, list[Float[np.ndarray, "P _V 3"]]] = {}
        truth, scales = [], []
        for head in dataset.test[split]:
            _, operators, _, scale = head_inputs(head.vertices, head.faces, k=k)
            truth.append(head.displacements)
            scales.append(scale)
            found = head_predictions(
                dataset, head, models, rows, anchors, copy=True, operators=operators
            )
            for name, p in found.items():
                predicted.setdefault(name, []).append(p)
            for name in rows:
                pen[name].append(penetration(head, found[name], part_names))
            pen["ground_truth"].append(penetration(head, head.displacements, part_names))
            out["examples"].setdefault(split, (head, found))
            print(f"evaluated {head.name}")
        for name, p in predicted.items():
            test.setdefault(name, {})[split] = split_errors(p, truth, scales)
        if split == HELDOUT_SPLIT:
            out["predictions"] = {"no_motion": [np.zeros_like(t) for t in truth], **predicted}
            out["truth"] = truth
    out["test"] = test
    out["penetration"] = {name: float(np.mean(v)) for name, v in pen.items()}
    return out


def heldout_shapes(
    heads: Sequence[RiggedHead],
    predicted: Mapping[str, Sequence[Float[np.ndarray, "P _V 3"]]],
    poses: PoseSet,
) -> dict:
    """Per single expression on held-out ICT heads: ``sculpted_shape_errors`` of each row's
    first ``poses.n_basis`` poses against each head's ground truth on its skin (parts 0 and 1:
    face, head and neck), then the mean over heads. ``predicted``: row -> (P, V, 3) per head
    of ``heads`` (a ``no_motion`` row is left out).

    Returns {"labels": the A basis names, "upper_face": (A,) bool (``UPPER_FACE``),
    "methods": row -> {"skin_mae_mm", "amplitude_ratio", "peak_ratio"} (A,) each}, as lists.
    An aggregate MAE can hide a region that never moves: most vertices of an eye or brow
    shape are static."""
    n = poses.n_basis
    methods = {}
    for name, per_head in predicted.items():
        if name == "no_motion":
            continue
        records = []
        for head, p in zip(heads, per_head, strict=True):
            e = sculpted_shape_errors(p[:n], head.displacements[:n], head.parts <= 1)
            records.append({**e, "peak_ratio": e["peak_mm"] / e["target_peak_mm"]})
        methods[name] = {
            k: np.mean([r[k] for r in records], axis=0).tolist()
            for k in ("skin_mae_mm", "amplitude_ratio", "peak_ratio")
        }
    labels = [str(name) for name in poses.basis_names]
    return {
        "labels": labels,
        "upper_face": [name.startswith(UPPER_FACE) for name in labels],
        "methods": methods,
    }


def clean_penetration(
    heads: Sequence[RiggedHead],
    predicted: Mapping[str, Sequence[Float[ArrayLike, "P _V 3"]]],
    poses: PoseSet,
    part_names: Sequence[str],
) -> dict:
    """Penetration where the ground truth has none (``penetration_free_set``: per head, the
    inner vertices inside the skin at rest and the poses whose ground truth pushes none of
    them out) of each row of ``predicted`` (row -> (P, V, 3) per head, cm) and of the ground
    truth, and the plain penetration (``inner_outside``'s mean) re-measured.

    Returns results.json's ``penetration_clean`` (row -> {"fraction": outside fraction over
    the selected (pose, vertex) pairs of all heads, "poses_with_any": fraction of selected
    (head, pose) pairs with any vertex outside}), ``penetration_clean_protocol`` and
    ``penetration_remeasured`` (row -> mean over heads of the outside fraction)."""
    predicted = {**predicted, "ground_truth": [head.displacements for head in heads]}
    clean: dict[str, list[Bool[np.ndarray, "Q N"]]] = {name: [] for name in predicted}
    plain: dict[str, list[float]] = {name: [] for name in predicted}
    chosen, kept_vertices = [], []
    for i, head in enumerate(heads):
        pose_index, vertices = penetration_free_set(head, part_names)
        chosen.append(pose_index)
        kept_vertices.append(int(vertices.sum()))
        for name, displacements in predicted.items():
            outside = inner_outside(head, displacements[i], part_names)
            plain[name].append(float(outside.mean()))
            clean[name].append(outside[pose_index][:, vertices])
        print(f"{head.name}: {pose_index.size} of {poses.n_poses} poses without penetration")
    counts = np.bincount(np.concatenate(chosen), minlength=poses.n_poses)
    return {
        "penetration_clean": {
            name: {
                "fraction": float(np.mean(np.concatenate([o.ravel() for o in outs]))),
                "poses_with_any": float(np.mean(np.concatenate([o.any(axis=1) for o in outs]))),
            }
            for name, outs in clean.items()
        },
        "penetration_clean_protocol": {
            "split": HELDOUT_SPLIT,
            "heads": len(chosen),
            "selection": "per head: inner vertices (teeth, gums, eyeballs) inside the skin at "
            "rest; poses whose ground truth pushes none of them outside (threshold 0)",
            "fraction": "outside fraction over the selected (pose, vertex) pairs of all heads",
            "poses_with_any": "fraction of selected (head, pose) pairs with any vertex outside",
            "poses_per_head": [int(c.size) for c in chosen],
            "inner_vertices_per_head": kept_vertices,
            "poses_selected_on_every_head": [
                poses.labels[i] for i in np.flatnonzero(counts == len(chosen))
            ],
        },
        "penetration_remeasured": {n: float(np.mean(v)) for n, v in plain.items()},
    }


def placement_errors(
    model: RigAnyFace, poses: PoseSet, dataset: AutorigDataset, model_name: str = "raf"
) -> tuple[dict, dict]:
    """A pure model placed in the unit sphere by the head's bounding box (as trained) and by
    ``face_placement``, on each ``HELDOUT_SPLIT`` head of ``dataset`` whole and cut below the
    chin (``crop_below_chin``, 1 cm), compared on the vertices above the cut.

    Returns (``"<whole|cut>/<bounding_box|face>"`` -> ``error_stats`` over the heads (mm),
    the protocol's record: the mean scales (cm) of both placements on both crops, the median
    seconds of a face fit, and how it was done; ``model_name`` names the model there)."""
    errors: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    scales: dict[str, list[dict]] = {"whole": [], "cut": []}
    fit_seconds = []
    for head in dataset.test[HELDOUT_SPLIT]:
        cut, kept = crop_below_chin(head)
        truth = head.displacements[:, kept]
        for crop, mesh in (("whole", head), ("cut", cut)):
            start = time.perf_counter()
            placement = face_placement(dataset, mesh.vertices, mesh.faces)
            fit_seconds.append(time.perf_counter() - start)
            _, _, box_scale = normalise(mesh.vertices)
            scales[crop].append({"bounding_box_cm": box_scale, "face_cm": placement[1]})
            for how, where in (("bounding_box", None), ("face", placement)):
                predicted = generate_rig(
                    model, poses, mesh.vertices, mesh.faces, placement=where
                ).displacements
                if crop == "whole":
                    predicted = predicted[:, kept]  # compared on the vertices both share
                errors.setdefault(f"{crop}/{how}", []).append((predicted, truth))
        print(f"{head.name}: {int(kept.sum())} of {head.n_vertices} vertices above the cut")
    stats = {
        key: error_stats(
            np.concatenate([p for p, _ in pairs], 1), np.concatenate([t for _, t in pairs], 1)
        )
        for key, pairs in errors.items()
    }
    protocol = {
        "split": HELDOUT_SPLIT,
        "heads": len(dataset.test[HELDOUT_SPLIT]),
        "model": model_name,
        "cut": "triangles reaching below the chin landmark minus 1 cm removed",
        "compared_on": "the vertices above the cut (both crops)",
        "face": "face_placement: trimmed-ICP similarity of the ICT face part, the generic ICT "
        "head's bounding-box centre and radius carried through it",
        "scale_cm": {
            crop: {k: float(np.mean([s[k] for s in v])) for k in v[0]} for crop, v in scales.items()
        },
        "seconds_face_fit_median": float(np.median(fit_seconds)),
    }
    return stats, protocol
