"""A Gaussian width that holds up with few edits: leave-one-out, one standard error.

``fit_sigma`` minimises the leave-one-out (LOO) error of the edits. With few edits that
minimum is a poor guide to the frames nobody edited: the edits sit at the most problematic
poses, far apart, and the widest Gaussians predict one such pose from the others best while
they spread the correction over every frame in between (10 real ICT edits: the LOO width makes
WPSE worse than no correction on held-out frames). ``fit_width`` keeps the leave-one-out
criterion but measures it the way the user sees it and trusts it only as far as the edits
support it:

- the error of edit i left out is the mean distance, over the edited vertices, between the
  sculpted shape and the rig corrected by the other edits (Rippa's closed form,
  ``loo_residuals``), so every vertex counts as much as in a per-vertex error map;
- the width is the *smallest* one whose mean LOO error is within ``se_factor`` standard errors
  (over the P edits) of the minimum: the one-standard-error rule of cross-validation. With few
  edits the standard error is large and the rule shrinks the correction towards none far from
  the edits; with many it approaches the LOO minimum.

The minimum is found on a dense log-spaced grid (the curve is flat and not convex; a grid is
what the one-standard-error rule needs anyway).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._pse import EditData
from ._sigma import loo_residuals


@dataclasses.dataclass(frozen=True)
class WidthFit:
    """Result of ``fit_width`` (its docstring lists the fields)."""

    sigma: float
    loo_min_sigma: float
    grid: Float[np.ndarray, " G"]
    loo_mean: Float[np.ndarray, " G"]
    loo_per_edit: Float[np.ndarray, "G P"]
    standard_error: float
    se_factor: float


@jax.jit
def _loo_distance_per_edit(metric, poses, displacements, sigma, ridge, scored):
    residual = loo_residuals(metric, poses, displacements, sigma, ridge)  # (S, P, 3)
    distance = jnp.sqrt(jnp.sum(residual**2, axis=-1) + 1e-30)
    return jnp.mean(distance, axis=0)[scored]


def loo_distance_per_edit(
    data: EditData, sigma: Float[ArrayLike, ""], ridge: float = 1e-6, max_vertices: int = 500
) -> Float[Array, " P"]:
    """Mean over the edited vertices (every k-th when more than ``max_vertices``) of the
    distance between edit i and its leave-one-out prediction, for every edit i that was
    sculpted (a rest-pose anchor, which is exact by construction, is not scored)."""
    metric, poses, displacements = _vertex_sample(data, max_vertices)
    return _loo_distance_per_edit(
        metric, poses, displacements, jnp.float32(sigma), ridge, jnp.asarray(_scored(data))
    )


def _scored(data: EditData) -> np.ndarray:
    """Edits that count in the error: all but a zero edit at the rest pose (the anchor)."""
    poses = np.asarray(data.poses)
    still = np.all(np.asarray(data.displacements) == 0, axis=(0, 2))
    anchor = np.all(poses == 0, axis=1) & still
    return np.flatnonzero(~anchor)


def _vertex_sample(data: EditData, max_vertices: int):
    s = data.displacements.shape[0]
    stride = max(1, -(-s // max_vertices))
    displacements = data.displacements[::stride]
    metric = data.metric[::stride] if data.metric.shape[0] > 1 else data.metric
    return metric, data.poses, displacements


def default_width_grid(data: EditData, size: int = 41) -> Float[np.ndarray, " size"]:
    """``size`` widths log-spaced over [0.02, 5] times the median pairwise edit distance
    under the mean metric (the same span as ``fit_sigma``'s grid, four times denser)."""
    poses = np.asarray(data.poses, np.float64)
    metric = np.asarray(data.metric, np.float64).mean(axis=0)
    diff = (poses[:, None] - poses[None]) ** 2
    pair = np.sqrt(np.maximum(diff @ metric, 0.0))[np.triu_indices(poses.shape[0], 1)]
    median = float(np.median(pair[pair > 0])) if np.any(pair > 0) else 1.0
    return median * np.geomspace(0.02, 5.0, size)


def fit_width(
    data: EditData,
    *,
    se_factor: float = 1.0,
    grid: Float[np.ndarray, " G"] | None = None,
    ridge: float = 1e-6,
    max_vertices: int = 500,
) -> WidthFit:
    """Width of prepared edits (``prepare_edits``) by the one-standard-error LOO rule.

    Args:
        data: prepared edits (at least 3 sculpted ones: a standard error needs two
            left-out errors and each left-out model at least one edit).
        se_factor: multiple of the standard error (>= 0; 0 gives the LOO minimum).
        grid: widths to search (default ``default_width_grid``).
        ridge: diagonal added to every basis matrix.
        max_vertices: vertices scored (every k-th of the edited vertices).

    Returns:
        A ``WidthFit`` with ``sigma``, the chosen width (the smallest within ``se_factor``
        standard errors of the minimum); ``loo_min_sigma``, the grid width with the smallest
        mean LOO error; ``grid`` (G,) the widths, ``loo_mean`` (G,) their mean LOO error
        (units of the edits, mean distance per vertex) and ``loo_per_edit`` (G, P) the error
        of each left-out edit; ``standard_error``, the standard error of the mean LOO error at
        ``loo_min_sigma``; ``se_factor``, the rule's multiple of it.
    """
    scored = _scored(data)
    if scored.size < 3:
        raise ValueError(
            f"data: the one-standard-error width needs at least 3 sculpted edits, got {scored.size}"
        )
    if not np.isfinite(se_factor) or se_factor < 0:
        raise ValueError(f"se_factor: expected a finite value >= 0, got {se_factor}")
    if max_vertices < 1:
        raise ValueError(f"max_vertices: expected >= 1, got {max_vertices}")
    grid = default_width_grid(data) if grid is None else np.asarray(grid, np.float64)
    if grid.ndim != 1 or grid.size == 0 or np.any(~np.isfinite(grid)) or np.any(grid <= 0):
        raise ValueError("grid: expected a non-empty 1-D array of finite widths > 0")
    grid = np.sort(grid)
    per_edit = np.stack(
        [np.asarray(loo_distance_per_edit(data, s, ridge, max_vertices)) for s in grid]
    )  # (G, P)
    finite = np.all(np.isfinite(per_edit), axis=1)
    if not np.any(finite):
        raise ValueError("grid: the leave-one-out error is not finite at any width")
    mean = np.where(finite, per_edit.mean(axis=1), np.inf)
    best = int(np.argmin(mean))
    standard_error = float(per_edit[best].std(ddof=1) / np.sqrt(per_edit.shape[1]))
    within = np.flatnonzero(mean <= mean[best] + se_factor * standard_error)
    chosen = int(within[0])  # the smallest width within the band (always <= best)
    return WidthFit(
        sigma=float(grid[chosen]),
        loo_min_sigma=float(grid[best]),
        grid=grid,
        loo_mean=mean,
        loo_per_edit=per_edit,
        standard_error=standard_error,
        se_factor=float(se_factor),
    )
