"""How fast a correction changes over a take (Seol et al.'s Figure 6 asks that an edit change
smoothly over time)."""

import numpy as np
from jaxtyping import ArrayLike, Float


def temporal_change(
    frames: Float[ArrayLike, "T V 3"],
) -> dict[str, float | Float[np.ndarray, " T_1"]]:
    """How fast a per-vertex quantity (a correction, or the mesh itself) changes over a take.

    Returns ``max_step`` = max_t,v |x_{t+1,v} - x_{t,v}| (units per frame),
    ``max_acceleration`` = max_t,v |x_{t+1,v} - 2 x_{t,v} + x_{t-1,v}| (units per frame^2)
    and ``step`` (T-1,) the largest vertex step of each frame pair (Seol et al.'s Figure 6
    asks that an edit change smoothly over time, no faster than the take itself)."""
    frames = np.asarray(frames, np.float64)
    if frames.ndim != 3 or frames.shape[2] != 3 or frames.shape[0] < 3:
        raise ValueError(f"frames: expected shape (T, V, 3) with T >= 3, got {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise ValueError("frames: contains non-finite values")
    step = np.linalg.norm(np.diff(frames, axis=0), axis=2).max(axis=1)
    acceleration = np.linalg.norm(np.diff(frames, 2, axis=0), axis=2).max(axis=1)
    return {
        "max_step": float(step.max()),
        "max_acceleration": float(acceleration.max()),
        "step": step,
    }
