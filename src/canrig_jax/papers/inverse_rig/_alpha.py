"""The sparsity weight the inverse-rig evaluation reports each method at (Racković et al.'s
protocol): swept on training poses, then chosen by one rule."""

import numpy as np


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
