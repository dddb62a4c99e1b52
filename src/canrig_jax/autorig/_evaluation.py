"""The evaluation of an auto-rigger (issue 19): errors by pose class and vertex class, the
worst poses, and errors against a head's person-made targets over shared ARKit shapes.

* **Pose classes**: the single expressions (the pose set's first A poses) and the
  combinations (the rest).
* **Vertex classes**: for every (pose, vertex) pair, *static* when the ground-truth
  displacement is below ``STATIC_MM`` (0.01 mm), else *moving*; the two partition the pairs.
* **Sculpted targets** (MakeHuman): the skin (largest component), and *active* pairs whose
  sculpted displacement exceeds ``ACTIVE_MM`` (0.5 mm). ICT's split ``browInnerUp_L/_R`` and
  ``cheekPuff_L/_R`` are summed into the one ARKit shape (``shared_shape_matrix``).

Inputs are centimetres (ICT, MakeHuman after ``load_makehuman``); outputs millimetres.
"""

from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from .._metrics import CM_TO_MM
from ..data import to_arkit
from ._data import PoseSet

STATIC_MM = 0.01
ACTIVE_MM = 0.5


def pose_classes(poses: PoseSet) -> dict[str, Int[np.ndarray, " _n"]]:
    """{"single": the single-expression pose indices, "combinations": the others}."""
    a = poses.n_basis
    return {"single": np.arange(a), "combinations": np.arange(a, poses.n_poses)}


def static_mask(truth: Float[ArrayLike, "*batch V 3"]) -> Bool[np.ndarray, "*batch V"]:
    """(..., V) bool: ground-truth displacement (cm, (..., V, 3)) below ``STATIC_MM``."""
    return np.linalg.norm(np.asarray(truth, np.float64), axis=-1) * CM_TO_MM < STATIC_MM


def _distances_mm(predicted, truth) -> np.ndarray:
    predicted, truth = np.asarray(predicted, np.float64), np.asarray(truth, np.float64)
    if predicted.shape != truth.shape or predicted.ndim != 3 or predicted.shape[-1] != 3:
        raise ValueError(
            f"predicted: expected the ground truth's shape (P, V, 3) {truth.shape}, "
            f"got {predicted.shape}"
        )
    if not np.all(np.isfinite(predicted)):
        raise ValueError("predicted: contains non-finite displacements")
    return np.linalg.norm(predicted - truth, axis=-1) * CM_TO_MM


def class_errors(
    predicted: Sequence[Float[ArrayLike, "P _V 3"]],
    truth: Sequence[Float[ArrayLike, "P _V 3"]],
    poses: PoseSet,
) -> dict[str, dict[str, float]]:
    """Errors of several heads' predictions (each (P, V, 3), cm) by pose class.

    Returns {"single" | "combinations": {"mae_mm", "q95_mm", "static_mae_mm",
    "moving_mae_mm", "static_fraction"}}, every (pose, vertex) pair of every head counted
    once (heads of different vertex counts are pooled)."""
    if len(predicted) != len(truth) or not truth:
        raise ValueError(f"predicted: {len(predicted)} heads for {len(truth)} ground truths")
    out = {}
    for name, index in pose_classes(poses).items():
        distance, still = [], []
        for p, t in zip(predicted, truth, strict=True):
            if np.shape(t)[0] != poses.n_poses:
                raise ValueError(f"truth: {np.shape(t)[0]} poses, the pose set {poses.n_poses}")
            distance.append(_distances_mm(p, t)[index].ravel())
            still.append(static_mask(np.asarray(t)[index]).ravel())
        d, s = np.concatenate(distance), np.concatenate(still)
        out[name] = {
            "mae_mm": float(d.mean()),
            "q95_mm": float(np.percentile(d, 95)),
            "static_mae_mm": float(d[s].mean()) if s.any() else 0.0,
            "moving_mae_mm": float(d[~s].mean()) if (~s).any() else 0.0,
            "static_fraction": float(s.mean()),
        }
    return out


def worst_poses(
    predicted: Sequence[Float[ArrayLike, "P _V 3"]],
    truth: Sequence[Float[ArrayLike, "P _V 3"]],
    poses: PoseSet,
    n: int = 5,
) -> list[dict]:
    """The ``n`` poses with the largest MAE (mm) over all heads' vertices, largest first:
    [{"pose": label, "mae_mm": value}, ...]."""
    per_pose = np.concatenate(
        [_distances_mm(p, t) for p, t in zip(predicted, truth, strict=True)], axis=1
    ).mean(axis=1)
    order = np.argsort(-per_pose, kind="stable")[:n]
    return [{"pose": poses.labels[i], "mae_mm": float(per_pose[i])} for i in order]


def shared_shape_matrix(
    source_names: Sequence[str], target_names: Sequence[str]
) -> tuple[Int[np.ndarray, " S"], Float[np.ndarray, "S K_source"]]:
    """How a source rig's shapes (ICT) give a target rig's (ARKit), by ARKit name.

    Returns (target_index (S,), matrix (S, K_source)): the S target shapes with a source,
    and for each a row with 1 on every source shape of that ARKit name, so ``matrix @
    source_deltas`` sums ICT's halves ``browInnerUp_L + browInnerUp_R`` into ``browInnerUp``.
    Target shapes without a source (``tongueOut`` for ICT) are left out."""
    source = [to_arkit(str(n)) for n in source_names]
    target = [to_arkit(str(n)) for n in target_names]
    rows, kept = [], []
    for j, name in enumerate(target):
        ones = [i for i, s in enumerate(source) if s == name]
        if ones:
            row = np.zeros(len(source), np.float32)
            row[ones] = 1.0
            rows.append(row)
            kept.append(j)
    if not kept:
        raise ValueError("target_names: no shape shares an ARKit name with source_names")
    return np.asarray(kept, np.int64), np.stack(rows)


def _sculpted(predicted, truth, skin) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(S, V) error and target length in mm, and the per-shape record, computed once for
    ``sculpted_shape_errors`` and ``sculpted_target_errors``."""
    predicted = np.asarray(predicted, np.float64)
    truth = np.asarray(truth, np.float64)
    if predicted.ndim != 3 or predicted.shape != truth.shape or predicted.shape[-1] != 3:
        raise ValueError(
            f"predicted, truth: expected two (S, V, 3) arrays of one shape, got "
            f"{predicted.shape} and {truth.shape}"
        )
    skin = np.asarray(skin, bool)
    if skin.shape != (truth.shape[1],) or not skin.any():
        raise ValueError(f"skin: expected a non-empty (V,) mask, got shape {skin.shape}")
    distance = _distances_mm(predicted, truth)
    truth_mm = np.linalg.norm(truth, axis=-1) * CM_TO_MM
    predicted_mm = np.linalg.norm(predicted[:, skin], axis=-1) * CM_TO_MM
    per_shape = {
        "skin_mae_mm": distance[:, skin].mean(axis=1),
        "amplitude_ratio": predicted_mm.sum(1) / np.maximum(truth_mm[:, skin].sum(1), 1e-12),
        "peak_mm": predicted_mm.max(axis=1),
        "target_peak_mm": truth_mm[:, skin].max(axis=1),
    }
    return distance, truth_mm, per_shape


def sculpted_shape_errors(
    predicted: Float[ArrayLike, "S V 3"],
    truth: Float[ArrayLike, "S V 3"],
    skin: Bool[ArrayLike, " V"],
) -> dict[str, Float[np.ndarray, " S"]]:
    """Per shape, against person-made targets (each (S, V, 3), cm): where a generated rig
    fails, shape by shape.

    Returns {"skin_mae_mm": (S,) mean error over the skin vertices; "amplitude_ratio": (S,)
    the summed predicted displacement length over the summed target length on the skin (0 for
    no motion, 1 for the sculpted amount of motion); "peak_mm", "target_peak_mm": (S,) the
    largest skin displacement of the prediction and of the target}."""
    return _sculpted(predicted, truth, skin)[2]


def sculpted_target_errors(
    predicted: Float[ArrayLike, "S V 3"],
    truth: Float[ArrayLike, "S V 3"],
    skin: Bool[ArrayLike, " V"],
) -> dict[str, float]:
    """Errors against person-made targets (each (S, V, 3), cm).

    Returns {"skin_mae_mm", "skin_q95_mm": over the skin vertices of every shape;
    "active_mae_mm": over the (shape, vertex) pairs whose target moves more than
    ``ACTIVE_MM``; "amplitude_ratio_median": the median over shapes of the summed predicted
    displacement length over the summed target length on the skin (0 for no motion;
    ``sculpted_shape_errors`` gives it per shape)}."""
    distance, truth_mm, per_shape = _sculpted(predicted, truth, skin)
    skin = np.asarray(skin, bool)
    active = truth_mm > ACTIVE_MM
    return {
        "skin_mae_mm": float(distance[:, skin].mean()),
        "skin_q95_mm": float(np.percentile(distance[:, skin], 95)),
        "active_mae_mm": float(distance[active].mean()) if active.any() else 0.0,
        "amplitude_ratio_median": float(np.median(per_shape["amplitude_ratio"])),
    }
