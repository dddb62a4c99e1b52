"""Pieces of the WPSE evaluation protocol: which frames an artist would edit, and how much of
a correction survives at a probe pose (the locality measure of Seol et al.'s Figure 7)."""

import numpy as np
from jaxtyping import ArrayLike, Float, Int


def select_edit_frames(
    error: Float[ArrayLike, " T"],
    poses: Float[ArrayLike, "T K"],
    n_edits: int,
    min_distance: float,
) -> Int[np.ndarray, " P"]:
    """The ``n_edits`` most problematic frames, spread out in weight space.

    Greedy: frames in decreasing ``error``; a frame within ``min_distance`` (Euclidean, weight
    units) of one already chosen is skipped. The first n of a larger selection are the
    selection of size n. Raises ValueError when fewer than ``n_edits`` frames qualify.
    """
    error = np.asarray(error, np.float64)
    poses = np.asarray(poses, np.float64)
    if error.ndim != 1 or poses.ndim != 2 or poses.shape[0] != error.shape[0]:
        raise ValueError(
            f"error, poses: expected shapes (T,) and (T, K), got {error.shape} and {poses.shape}"
        )
    if n_edits < 1:
        raise ValueError(f"n_edits: expected >= 1, got {n_edits}")
    if not min_distance >= 0:
        raise ValueError(f"min_distance: expected >= 0, got {min_distance}")
    chosen: list[int] = []
    for frame in np.argsort(-error, kind="stable"):
        if all(np.linalg.norm(poses[frame] - poses[c]) >= min_distance for c in chosen):
            chosen.append(int(frame))
            if len(chosen) == n_edits:
                return np.asarray(chosen, np.int64)
    raise ValueError(
        f"n_edits: only {len(chosen)} frames are at least {min_distance} apart, {n_edits} requested"
    )


def retained_fraction(
    reference: Float[ArrayLike, "V 3"],
    probe: Float[ArrayLike, "V 3"],
    region: Int[ArrayLike, " R"],
) -> float:
    """Projection of the probe correction on the reference one over a vertex region,
    sum <c_probe, c_ref> / sum ||c_ref||^2 (1: kept entirely, 0: lost)."""
    region = np.asarray(region)
    reference = np.asarray(reference, np.float64)[region]
    probe = np.asarray(probe, np.float64)[region]
    energy = float(np.sum(reference**2))
    if energy == 0:
        raise ValueError("reference: the correction is zero on the region")
    return float(np.sum(reference * probe) / energy)
