"""The sparsity comparison of Racković et al. 2023 as a protocol: is the converged quartic
method's solution sparser than the least-squares baselines' at no loss of accuracy?

The rule is fixed before anything is measured on a test take: sweep the L1 weight alpha on
the case's own random sparse training poses (noisy, scored against the clean meshes), then
take **the largest alpha whose mean training RMSE is no higher than the lower of Joshi's and
Cetinaslan's training RMSE** (``sparsest_alpha_within``). Only then is the test take solved,
once, at that alpha, and ``sparsity_verdict`` says whether the cardinality there is at least
``SPARSITY_TARGET`` (15 %) below both baselines' at equal or lower test RMSE.
"""

from collections.abc import Callable, Sequence

import numpy as np
from jaxtyping import ArrayLike, Float

from ...inverse import AbstractInverseMethod, InverseProblem, solve_sequence, summarize
from ...rig import UNIT_IN_CM, BlendshapeRig, evaluate_batch

SPARSITY_TARGET = 0.15
"""Relative cardinality reduction the quartic method must reach against every baseline."""


def noisy_meshes(
    rig: BlendshapeRig,
    weights: Float[ArrayLike, "T K"],
    rng: np.random.Generator,
    noise_variance_cm2: float = 0.03,
) -> tuple[Float[np.ndarray, "T V 3"], Float[np.ndarray, "T V 3"]]:
    """(clean, noisy) float32 meshes of ``weights`` in rig units: the rig's meshes and the same
    plus N(0, ``noise_variance_cm2``) per coordinate (cm^2, converted to the rig's unit)."""
    if not noise_variance_cm2 >= 0:
        raise ValueError(f"noise_variance_cm2: expected >= 0, got {noise_variance_cm2}")
    clean = np.asarray(evaluate_batch(rig, np.asarray(weights, np.float32)), np.float32)
    sigma = np.sqrt(noise_variance_cm2) / UNIT_IN_CM[rig.units]
    return clean, (clean + rng.normal(0.0, sigma, clean.shape)).astype(np.float32)


def alpha_sweep(
    problem: InverseProblem,
    make_method: Callable[[float], AbstractInverseMethod],
    alphas_cm2: Sequence[float],
    noisy: Float[ArrayLike, "T V 3"],
    clean: Float[ArrayLike, "T V 3"],
) -> list[dict]:
    """One row per alpha (cm^2; ``make_method`` receives it in the rig's squared unit): the
    ``summarize`` metrics of ``solve_sequence`` on ``noisy`` against ``clean``, with the mean
    steps and the fraction of frames whose ``result`` is successful."""
    rig = problem.rig
    scale = UNIT_IN_CM[rig.units] ** 2  # alpha is in squared length units
    rows = []
    for alpha in alphas_cm2:
        solution = solve_sequence(problem, noisy, make_method(float(alpha) / scale))
        rows.append(
            {
                "alpha": float(alpha),
                **summarize(rig, np.asarray(solution.weights), clean),
                "steps_mean": float(np.mean(np.asarray(solution.stats["steps"]))),
                "converged_fraction": float(np.mean(np.asarray(solution.stats["converged"]))),
            }
        )
    return rows


def sparsest_alpha_within(sweep: list[dict], rmse_limit_mm: float) -> dict | None:
    """The selection rule: the row of ``sweep`` (training poses) with the largest alpha whose
    ``rmse_mean_mm`` is <= ``rmse_limit_mm`` (the lower of the baselines' training RMSE);
    None when no alpha is that accurate. Raises a ValueError for rows without a finite RMSE."""
    if not sweep:
        raise ValueError("sweep: expected at least one row")
    if not np.isfinite(rmse_limit_mm):
        raise ValueError(f"rmse_limit_mm: expected a finite RMSE, got {rmse_limit_mm}")
    bad = [row.get("alpha") for row in sweep if not np.isfinite(row.get("rmse_mean_mm", np.nan))]
    if bad:
        raise ValueError(f"sweep: non-finite or missing rmse_mean_mm at alpha {bad}")
    within = [row for row in sweep if row["rmse_mean_mm"] <= rmse_limit_mm]
    return max(within, key=lambda row: row["alpha"]) if within else None


def sparsity_verdict(
    candidate: dict, baselines: dict[str, dict], target: float = SPARSITY_TARGET
) -> dict:
    """Whether ``candidate`` (``summarize`` metrics on the test take) is at least ``target``
    sparser than every baseline at equal or lower RMSE.

    Returns ``reduction`` (baseline -> 1 - cardinality / baseline's cardinality),
    ``rmse_at_most`` (baseline -> candidate RMSE <= baseline's), and ``met`` (all hold)."""
    if not baselines:
        raise ValueError("baselines: expected at least one baseline")
    reduction = {
        name: 1.0 - candidate["cardinality"] / row["cardinality"] for name, row in baselines.items()
    }
    rmse_at_most = {
        name: bool(candidate["rmse_mean_mm"] <= row["rmse_mean_mm"])
        for name, row in baselines.items()
    }
    met = all(r >= target for r in reduction.values()) and all(rmse_at_most.values())
    return {"reduction": reduction, "rmse_at_most": rmse_at_most, "met": bool(met)}
