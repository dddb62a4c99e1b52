"""The protocol for choosing the temporal inverse rig's smoothness on training data only.

Training takes are synthetic: random sparse key poses (``rig.random_sparse_poses``, as the
alpha protocol's training poses) held at key times a random 0.2-0.6 s apart and eased from
one to the next with a cosine ramp, sampled at the capture's frame rate; noise is added as
for the test take. ``select_smoothness`` then takes the largest smoothness whose mean
training RMSE is within 5 % of the per-frame solve's (smoothness 0): the smoothest weights
that cost practically nothing in accuracy, the same kind of rule as ``select_alpha``.
"""

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float32

from ..rig import random_sparse_poses

KEY_SPACING_S = (0.2, 0.6)
"""Range of the random time between two key poses of a training take (seconds)."""


def smooth_training_takes(
    rng: np.random.Generator,
    names: Sequence[str],
    n_takes: int,
    n_frames: int,
    fps: float,
    key_spacing_s: tuple[float, float] = KEY_SPACING_S,
) -> Float32[np.ndarray, "n_takes T K"]:
    """(n_takes, n_frames, K) weights: random sparse key poses (``random_sparse_poses``) at
    key times ``key_spacing_s`` seconds apart (uniform), cosine-eased between keys, sampled at
    ``fps``. Weights stay in [0, 1] (each frame is a convex combination of two keys)."""
    if n_takes < 1 or n_frames < 3:
        raise ValueError(f"n_takes, n_frames: expected >= 1 and >= 3, got {n_takes}, {n_frames}")
    if not fps > 0:
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    low, high = key_spacing_s
    if not 0 < low <= high:
        raise ValueError(f"key_spacing_s: expected 0 < low <= high, got {key_spacing_s}")
    duration = (n_frames - 1) / fps
    takes = []
    for _ in range(n_takes):
        times = [0.0]
        while times[-1] < duration:
            times.append(times[-1] + rng.uniform(low, high))
        keys = random_sparse_poses(rng, len(times), names)
        t = np.arange(n_frames) / fps
        segment = np.searchsorted(times, t, side="right") - 1
        segment = np.minimum(segment, len(times) - 2)
        start, end = np.asarray(times)[segment], np.asarray(times)[segment + 1]
        ease = 0.5 - 0.5 * np.cos(np.pi * np.clip((t - start) / (end - start), 0.0, 1.0))
        frames = (1 - ease)[:, None] * keys[segment] + ease[:, None] * keys[segment + 1]
        takes.append(frames.astype(np.float32))
    return np.stack(takes)


def select_smoothness(sweep: list[dict], tolerance: float = 0.05) -> dict:
    """The sweep row chosen for the temporal solve: the largest ``smoothness`` whose
    ``rmse_mean_mm`` is within ``tolerance`` (relative) of the row with smoothness 0 (the
    per-frame solve), which the sweep must contain. Raises a ValueError for a missing or
    non-finite RMSE instead of choosing among the rest."""
    if not any(row.get("smoothness") == 0 for row in sweep):
        raise ValueError("sweep: expected a row with smoothness 0 (the per-frame baseline)")
    failed = [r.get("smoothness") for r in sweep if not np.isfinite(r.get("rmse_mean_mm", np.nan))]
    if failed:
        raise ValueError(f"sweep: non-finite or missing rmse_mean_mm at smoothness {failed}")
    baseline = next(row for row in sweep if row["smoothness"] == 0)["rmse_mean_mm"]
    near = [row for row in sweep if row["rmse_mean_mm"] <= (1.0 + tolerance) * baseline]
    return max(near, key=lambda row: row["smoothness"])
