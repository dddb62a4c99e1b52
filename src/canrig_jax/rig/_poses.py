"""Pose sets for experiments: random sparse weight vectors."""

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float32

from ._synthesis import MUTUALLY_EXCLUSIVE, exclusive_pairs


def random_sparse_poses(
    rng: np.random.Generator,
    n_poses: int,
    names: Sequence[str],
    n_active: tuple[int, int] = (4, 10),
    exclude: Sequence[tuple[str, str]] = MUTUALLY_EXCLUSIVE,
) -> Float32[np.ndarray, "n_poses K"]:
    """(n_poses, K) float32 poses with between ``n_active`` active weights, each U(0, 1).

    The active set is drawn uniformly without replacement; a set holding both names of an
    ``exclude`` pair (opposite directions of one control, matched by canonical ARKit name, so
    any spelling) is redrawn.
    """
    low, high = n_active
    if not 1 <= low <= high <= len(names):
        raise ValueError(f"n_active: expected 1 <= low <= high <= {len(names)}, got {n_active}")
    if n_poses < 0:
        raise ValueError(f"n_poses: expected >= 0, got {n_poses}")
    banned = exclusive_pairs(names, exclude)
    poses = np.zeros((n_poses, len(names)), np.float32)
    for row in range(n_poses):
        while True:
            active = rng.choice(len(names), size=rng.integers(low, high + 1), replace=False)
            chosen = set(active.tolist())
            if not any(a in chosen and b in chosen for a, b in banned):
                break
        poses[row, active] = rng.uniform(0.0, 1.0, size=active.size)
    return poses
