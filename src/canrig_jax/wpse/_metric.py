"""Per-vertex pose-space metrics: the weighted distance of WPSE and the Euclidean one of PSE.

Seol et al., "Weighted pose space editing", eq. (6): the distance between poses w and w_i seen
from vertex v weights each blendshape by how much it moves v,

    ||w - w_i||_v = (sum_j alpha_{v,j} (w_j - w_{j,i})^2)^(1/2),
    alpha_{v,j} = (l_{v,j} + epsilon) / sum_j (l_{v,j} + epsilon),

with l_{v,j} the length of blendshape j's offset at v. The small ``epsilon`` (relative to the
largest offset of the rig) gives every blendshape a little weight everywhere, so two distinct
poses are never at distance zero and no per-vertex basis matrix is singular.

A metric is stored as a (S, K) array of per-vertex weights, or (1, K) when every vertex shares
it (PSE: all ones, the Euclidean distance), so one code path serves both.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


def blendshape_metric(
    deltas: Float[ArrayLike, "K V 3"], epsilon: float = 1e-3
) -> Float[np.ndarray, "V K"]:
    """alpha (V, K): per-vertex blendshape influence normalised to sum 1 (WPSE eq. (6)).

    ``epsilon`` is added to every offset length, in units of the largest offset length of
    the rig, before normalising (so vertices no shape moves get the uniform metric 1/K).
    """
    if not np.isfinite(epsilon) or epsilon <= 0:
        raise ValueError(f"epsilon: expected a finite value > 0, got {epsilon}")
    deltas = np.asarray(deltas, np.float64)
    if deltas.ndim != 3 or deltas.shape[2] != 3:
        raise ValueError(f"deltas: expected shape (K, V, 3), got {deltas.shape}")
    length = np.linalg.norm(deltas, axis=2).T  # (V, K)
    length = length + epsilon * max(float(length.max(initial=0.0)), 1e-30)
    return (length / length.sum(axis=1, keepdims=True)).astype(np.float32)


def euclidean_metric(n_blendshapes: int) -> Float[np.ndarray, "1 K"]:
    """The metric of plain PSE (Lewis et al. 2000): unit weight on every blendshape."""
    return np.ones((1, n_blendshapes), np.float32)


def pose_distance_sq(
    metric: Float[ArrayLike, "#S K"],
    weights: Float[ArrayLike, " K"],
    poses: Float[ArrayLike, "P K"],
) -> Float[Array, "#S P"]:
    """Squared per-vertex distances sum_j alpha_{v,j} (w_j - w_{j,i})^2 as one matmul.

    The (K, P) right operand is padded with zero columns to ``dot_width(P)`` and the product
    sliced back (exact: the padding only adds columns that are dropped)."""
    metric, weights, poses = jnp.asarray(metric), jnp.asarray(weights), jnp.asarray(poses)
    diff_sq = (weights[None, :] - poses) ** 2  # (P, K)
    p = poses.shape[0]
    diff_sq = jnp.pad(diff_sq, ((0, dot_width(p) - p), (0, 0)))
    return (metric @ diff_sq.T)[:, :p]


def dot_width(p: int) -> int:
    """Columns the (S, K) x (K, P) distance product is computed with: 16 up to 16, else the
    next multiple of 32. XLA's CPU matmul is much slower for other widths; measured on this
    project's 2-core machine at S = 19,190, K = 53 (ms per product, ``benchmarks/bench_wpse.py``
    re-measures it): P = 50 1.59 against 1.12 at 64, 48 1.30 against 1.12 at 64, 10 0.75
    against 0.64 at 16, 100 2.57 against 1.99 at 128."""
    return 16 if p <= 16 else -(-p // 32) * 32


def pairwise_pose_distance_sq(
    metric: Float[ArrayLike, "#S K"], poses: Float[ArrayLike, "P K"]
) -> Float[Array, "#S P P"]:
    """Squared per-vertex distances between all pairs of poses (the basis matrices' input)."""
    metric, poses = jnp.asarray(metric), jnp.asarray(poses)
    diff_sq = (poses[:, None, :] - poses[None, :, :]) ** 2  # (P, P, K)
    p = poses.shape[0]
    return (metric @ diff_sq.reshape(p * p, -1).T).reshape(-1, p, p)


def gaussian_kernel(
    distance_sq: Float[Array, "*shape"], sigma: Float[ArrayLike, ""] | Float[Array, "*#shape"]
) -> Float[Array, "*shape"]:
    """phi(r) = exp(-r^2 / (2 sigma^2))."""
    return jnp.exp(-distance_sq / (2.0 * jnp.square(sigma)))
