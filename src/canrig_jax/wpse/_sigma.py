"""The Gaussian width sigma: the paper's GUI mapping and a default fitted by leave-one-out.

GUI mapping (Seol et al., section 3.3): a slider value sigma_G in (0, 1) maps to

    sigma = lambda sqrt(-1 / log sigma_G) + c,

with lambda and c chosen so that sigma = sigma_G at sigma_G = 0.01 and at 0.99. The map is
increasing; below ``GUI_MIN`` (about 6.4e-4) it would give sigma <= 0 and is rejected.

Leave-one-out fit: for an interpolant with basis matrix Phi_v and coefficients X_v = Phi_v^-1 D_v,
the error at edit i when edit i is left out is X_{v,i} / (Phi_v^-1)_{ii} (Rippa 1999), so the
LOO error of every edit needs one factorisation per vertex. ``fit_sigma`` minimises the mean
squared LOO error over log sigma with ``optimistix.BFGS``, started from the best point of a
coarse log-spaced grid (the LOO curve is not convex in general).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from .._linalg import inv
from ._pse import EditData, basis_matrices

_LOW, _HIGH = 0.01, 0.99


def _gui_feature(sigma_g):
    return np.sqrt(-1.0 / np.log(sigma_g))


GUI_SCALE = (_HIGH - _LOW) / (_gui_feature(_HIGH) - _gui_feature(_LOW))
"""lambda of the GUI mapping (about 0.103)."""
GUI_OFFSET = _LOW - GUI_SCALE * _gui_feature(_LOW)
"""c of the GUI mapping (about -0.038)."""
GUI_MIN = float(np.exp(-1.0 / (GUI_OFFSET / GUI_SCALE) ** 2))
"""Smallest slider value giving sigma > 0."""


def sigma_from_gui(sigma_g: float) -> float:
    """sigma = lambda sqrt(-1 / log sigma_G) + c (the GUI mapping)."""
    value = float(sigma_g)
    if not np.isfinite(value) or not 0.0 < value < 1.0:
        raise ValueError(f"sigma_g: expected a value in (0, 1), got {sigma_g}")
    if value <= GUI_MIN:
        raise ValueError(
            f"sigma_g: values at or below {GUI_MIN:.3g} map to sigma <= 0, got {sigma_g}"
        )
    return float(GUI_SCALE * _gui_feature(value) + GUI_OFFSET)


def gui_from_sigma(sigma: float) -> float:
    """The slider value giving ``sigma`` (inverse of ``sigma_from_gui``)."""
    value = float(sigma)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"sigma: expected a finite value > 0, got {sigma}")
    feature = (value - GUI_OFFSET) / GUI_SCALE
    return float(np.exp(-1.0 / feature**2))


def loo_residuals(
    metric: Float[ArrayLike, "#S K"],
    poses: Float[ArrayLike, "P K"],
    displacements: Float[ArrayLike, "S P 3"],
    sigma: Float[ArrayLike, ""],
    ridge: float | Float[Array, ""] = 1e-6,
) -> Float[Array, "S P 3"]:
    """Leave-one-out errors X_{v,i} / (Phi_v^-1)_{ii} of every edit at every vertex."""
    metric, poses, displacements = (jnp.asarray(x) for x in (metric, poses, displacements))
    phi = basis_matrices(metric, poses, sigma, ridge)
    inverse = inv(phi)  # (S or 1, P, P)
    coefficients = jnp.einsum(
        "spq,sqc->spc",
        jnp.broadcast_to(inverse, (displacements.shape[0],) + inverse.shape[1:]),
        displacements,
    )
    diagonal = jnp.diagonal(inverse, axis1=-2, axis2=-1)[..., None]  # (S or 1, P, 1)
    return coefficients / diagonal


def loo_error(
    metric: Float[ArrayLike, "#S K"],
    poses: Float[ArrayLike, "P K"],
    displacements: Float[ArrayLike, "S P 3"],
    sigma: Float[ArrayLike, ""],
    ridge: float | Float[Array, ""] = 1e-6,
) -> Float[Array, ""]:
    """Mean over edits and vertices of the squared leave-one-out error."""
    residual = loo_residuals(metric, poses, displacements, sigma, ridge)
    return jnp.mean(jnp.sum(residual**2, axis=-1))


@dataclasses.dataclass(frozen=True)
class SigmaFit:
    """Result of ``fit_sigma`` (its docstring lists the fields)."""

    sigma: float
    loo_rms: float
    grid: Float[np.ndarray, " G"]
    grid_rms: Float[np.ndarray, " G"]
    successful: bool
    steps: int


def _subsample(data: EditData, max_vertices: int) -> tuple[Array, Array]:
    """The ``max_vertices`` vertices with the largest edits (all when fewer)."""
    displacements, metric = data.displacements, data.metric
    if displacements.shape[0] <= max_vertices:
        return metric, displacements
    magnitude = np.asarray(jnp.linalg.norm(displacements, axis=-1).max(axis=1))
    keep = np.sort(np.argsort(-magnitude)[:max_vertices])
    if metric.shape[0] > 1:
        metric = metric[keep]
    return metric, displacements[keep]


def fit_sigma(
    data: EditData,
    *,
    grid: Float[np.ndarray, " G"] | None = None,
    ridge: float = 1e-6,
    max_vertices: int = 300,
    max_steps: int = 32,
) -> SigmaFit:
    """Default sigma of prepared edits (``prepare_edits``) by leave-one-out, with optimistix.

    The LOO error uses the ``max_vertices`` vertices with the largest edits. ``grid``
    (default 16 widths log-spaced over [0.02, 5] times the median pairwise pose distance under
    the metric) picks the starting point; BFGS then minimises over log sigma.

    Returns:
        A ``SigmaFit`` with ``sigma``, the LOO-optimal width; ``loo_rms``, the root mean
        squared LOO error at ``sigma`` (units of the edits); ``grid`` (G,) the starting
        grid's widths and ``grid_rms`` their LOO RMS errors; ``successful``, whether
        optimistix reported success; ``steps``, the BFGS steps taken.
    """
    if data.poses.shape[0] < 2:
        raise ValueError("data: leave-one-out needs at least 2 edits")
    if max_vertices < 1:
        raise ValueError(f"max_vertices: expected >= 1, got {max_vertices}")
    metric, displacements = _subsample(data, max_vertices)
    poses = data.poses
    if grid is None:
        pair = np.asarray(
            jnp.sqrt(
                jnp.maximum(
                    metric.mean(axis=0)
                    @ ((poses[:, None] - poses[None]) ** 2).reshape(-1, poses.shape[1]).T,
                    0.0,
                )
            )
        )
        median = float(np.median(pair[pair > 0])) if np.any(pair > 0) else 1.0
        grid = median * np.geomspace(0.02, 5.0, 16)
    grid = np.asarray(grid, np.float64)
    if grid.ndim != 1 or grid.size == 0 or np.any(~np.isfinite(grid)) or np.any(grid <= 0):
        raise ValueError("grid: expected a non-empty 1-D array of finite widths > 0")

    scale = jnp.mean(jnp.sum(displacements**2, axis=-1))  # LOO error of sigma -> 0

    def objective(log_sigma, args):
        m, p, d = args
        value = loo_error(m, p, d, jnp.exp(log_sigma[0]), ridge) / scale
        return jnp.where(jnp.isfinite(value), value, jnp.inf)

    args = (metric, poses, displacements)
    jitted = jax.jit(objective)
    grid_loss = np.array([float(jitted(jnp.log(jnp.array([s], jnp.float32)), args)) for s in grid])
    start = float(grid[int(np.nanargmin(grid_loss))])
    solution = optx.minimise(
        objective,
        optx.BFGS(rtol=1e-3, atol=1e-4),
        jnp.log(jnp.array([start], jnp.float32)),
        args=args,
        max_steps=max_steps,
        throw=False,
    )
    sigma = float(jnp.exp(solution.value[0]))
    loss = float(jitted(solution.value, args))
    best_grid = float(np.nanmin(grid_loss))
    if not np.isfinite(loss) or loss > best_grid:  # keep the grid's best if BFGS wandered off
        sigma, loss = start, best_grid
    return SigmaFit(
        sigma=sigma,
        loo_rms=float(np.sqrt(loss * scale)),
        grid=grid,
        grid_rms=np.sqrt(grid_loss * float(scale)),
        successful=bool(solution.result == optx.RESULTS.successful),
        steps=int(solution.stats["num_steps"]),
    )
