"""CANRig's held-out data: the capture split in time and the random poses no training draw
shares (``experiments/canrig_eval.py``, the workflows and PBS protocols)."""

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float, Float32

from ...rig import random_sparse_poses


def split_capture(
    capture: Float[np.ndarray, "F K"],
) -> tuple[Float[np.ndarray, "_ K"], Float[np.ndarray, "_ K"]]:
    """(train, test): the first and second half of a capture (contiguous, so that no test
    frame has a neighbouring frame in the training set)."""
    half = len(capture) // 2
    return capture[:half], capture[half:]


def held_out_poses(
    capture_test: Float[np.ndarray, "F K"], names: Sequence[str], n_random: int = 100, seed: int = 1
) -> Float32[np.ndarray, "N K"]:
    """Held-out poses: the capture's test half and ``n_random`` random sparse poses drawn
    with a different seed than training (continuous weights: disjoint almost surely)."""
    random_poses = random_sparse_poses(np.random.default_rng(10_000 + seed), n_random, names)
    return np.concatenate([capture_test, random_poses]).astype(np.float32)
