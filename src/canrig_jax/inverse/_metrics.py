"""Inverse-rig metrics of Racković et al. 2023, reported in millimetres whatever the rig's unit
(``BlendshapeRig.units``: ICT is in cm, the MakeHuman head in dm).

Meshes are always reconstructed with the full rig (all corrective orders), whatever rig the
method assumed, and compared with the clean (noise-free) target.
"""

import jax
import numpy as np
from jaxtyping import ArrayLike, Float

from .._metrics import CM_TO_MM
from ..rig import UNIT_IN_CM, BlendshapeRig, evaluate


def mm_per_unit(rig: BlendshapeRig) -> float:
    """Millimetres in one unit of ``rig`` (10 for a rig in cm, 100 for one in dm)."""
    return UNIT_IN_CM[rig.units] * CM_TO_MM


CARDINALITY_TOL = 1e-3
"""A weight counts towards the cardinality when it exceeds this."""


def frame_metrics(
    rig: BlendshapeRig, weights: Float[ArrayLike, "T K"], clean: Float[ArrayLike, "T V 3"]
) -> dict[str, Float[np.ndarray, " T"]]:
    """Per-frame metrics of weights (T, K) against clean meshes (T, V, 3) in rig units.

    Returns (T,) arrays: ``rmse_mm`` = sqrt(||f(w) - b||^2 / V), ``p95_mm`` (95th percentile of
    per-vertex error), ``cardinality`` (weights > ``CARDINALITY_TOL``), ``l1``.
    """
    weights = np.asarray(weights)
    if weights.ndim != 2 or weights.shape[1] != rig.n_blendshapes:
        raise ValueError(f"weights: expected (T, {rig.n_blendshapes}), got {weights.shape}")
    if np.shape(clean) != (weights.shape[0], rig.n_vertices, 3):
        raise ValueError(
            f"clean: expected ({weights.shape[0]}, {rig.n_vertices}, 3), got {np.shape(clean)}"
        )
    meshes = np.asarray(jax.jit(jax.vmap(evaluate, (None, 0)))(rig, weights), np.float64)
    error = np.linalg.norm(meshes - np.asarray(clean, np.float64), axis=-1) * mm_per_unit(rig)
    return {
        "rmse_mm": np.sqrt((error**2).mean(axis=1)),
        "p95_mm": np.percentile(error, 95, axis=1),
        "cardinality": (weights > CARDINALITY_TOL).sum(axis=1).astype(np.float64),
        "l1": np.abs(weights).sum(axis=1),
    }


def roughness(weights: Float[ArrayLike, "T K"]) -> float:
    """sum_i sum_t (w_{t-1,i} - 2 w_{t,i} + w_{t+1,i})^2 over a take (T, K)."""
    weights = np.asarray(weights, np.float64)
    if weights.ndim != 2 or weights.shape[0] < 3:
        raise ValueError(f"weights: expected a take (T >= 3, K), got {weights.shape}")
    return float((np.diff(weights, n=2, axis=0) ** 2).sum())


def summarize(
    rig: BlendshapeRig, weights: Float[ArrayLike, "T K"], clean: Float[ArrayLike, "T V 3"]
) -> dict[str, float]:
    """Metrics of weights (T, K) against clean meshes (T, V, 3) in rig units, as in the paper's
    tables, each a mean over the frames, in mm whatever the rig's unit: ``rmse_mean_mm``, the
    per-frame RMSE sqrt(||f(w) - b||^2 / V); ``rmse_p95_mm``, the per-frame 95th percentile of
    the per-vertex error; ``cardinality``, the number of weights above ``CARDINALITY_TOL``;
    ``l1``, the sum of the weights."""
    m = frame_metrics(rig, weights, clean)
    return {
        "rmse_mean_mm": float(m["rmse_mm"].mean()),
        "rmse_p95_mm": float(m["p95_mm"].mean()),
        "cardinality": float(m["cardinality"].mean()),
        "l1": float(m["l1"].mean()),
    }
