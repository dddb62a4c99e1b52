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
    """Means over frames of ``frame_metrics``, with ``rmse_mean_mm`` (mean of per-frame RMSE)
    and ``rmse_p95_mm`` (mean of per-frame p95 error), as in the paper's tables."""
    m = frame_metrics(rig, weights, clean)
    return {
        "rmse_mean_mm": float(m["rmse_mm"].mean()),
        "rmse_p95_mm": float(m["p95_mm"].mean()),
        "cardinality": float(m["cardinality"].mean()),
        "l1": float(m["l1"].mean()),
    }


def select_alpha(sweep: list[dict], tolerance: float = 0.05, method: str = "") -> dict:
    """The sweep row chosen for a method: the largest alpha whose mean RMSE is within
    ``tolerance`` (relative) of the best mean RMSE of the sweep, i.e. the sparsest solution
    that is practically as accurate as the best one.

    Raises a ValueError naming ``method`` and the alphas whose RMSE is missing or not finite
    (a failed solve), instead of choosing among the rows that are left."""
    who = f" for method {method!r}" if method else ""
    if not sweep:
        raise ValueError(f"sweep: expected at least one row{who}")
    failed = [
        row.get("alpha")
        for row in sweep
        if not np.isfinite(row.get("rmse_mean_mm", np.nan)) or "alpha" not in row
    ]
    if failed:
        raise ValueError(
            f"sweep: non-finite or missing rmse_mean_mm{who} at alpha {failed}; "
            "the solver failed there"
        )
    best = min(row["rmse_mean_mm"] for row in sweep)
    near = [row for row in sweep if row["rmse_mean_mm"] <= (1.0 + tolerance) * best]
    return max(near, key=lambda row: row["alpha"])
