"""Search of pre-sculpted edits by region of interest (Seol et al., section 4).

An artist selects a region of interest (a vertex set) on the current pose w; every stored edit
pose w^p is scored by its weighted distance summed over the region,

    E(w^p) = sum_{v in ROI} (sum_j alpha_{v,j} (w_j - w^p_j)^2)^(1/2),

so only the blendshapes that move the region matter. Candidates with E < tau, sorted by E.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._metric import pose_distance_sq


@jax.jit
def region_energy(
    metric: Float[Array, "R K"], query: Float[Array, " K"], library: Float[Array, "N K"]
) -> Float[Array, " N"]:
    """E of every library pose for the region whose metric rows are given."""
    return jnp.sum(jnp.sqrt(jnp.maximum(pose_distance_sq(metric, query, library), 0.0)), axis=0)


@dataclasses.dataclass(frozen=True)
class SearchResult:
    """Result of ``search_edits`` (its docstring lists the fields)."""

    indices: Int[np.ndarray, " M"]
    energies: Float[np.ndarray, " M"]


def search_edits(
    metric: Float[ArrayLike, "V K"],
    library: Float[ArrayLike, "N K"],
    query: Float[ArrayLike, " K"],
    roi: Int[ArrayLike, " R"],
    tau: float = np.inf,
) -> SearchResult:
    """Library poses similar to ``query`` on the region ``roi`` (E < ``tau``), sorted.

    Args:
        metric: (V, K) per-vertex blendshape weights (``blendshape_metric(rig.deltas)``).
        library: (N, K) poses of the stored edits.
        query: (K,) the current pose.
        roi: (R,) distinct vertex indices, R >= 1.
        tau: energy threshold (> 0; default keeps every candidate).

    Returns:
        A ``SearchResult``: the candidates below the threshold, ``indices`` (M,) into the
        library, best first, and their ``energies`` (M,).
    """
    metric = np.asarray(metric, np.float32)
    library = np.asarray(library, np.float32)
    query = np.asarray(query, np.float32)
    roi = np.asarray(roi)
    if metric.ndim != 2:
        raise ValueError(f"metric: expected shape (V, K), got {metric.shape}")
    v, k = metric.shape
    if library.ndim != 2 or library.shape[1] != k:
        raise ValueError(f"library: expected shape (N, {k}), got {library.shape}")
    if query.shape != (k,):
        raise ValueError(f"query: expected shape ({k},), got {query.shape}")
    if roi.ndim != 1 or roi.size == 0:
        raise ValueError(f"roi: expected a non-empty 1-D vertex set, got shape {roi.shape}")
    if not np.issubdtype(roi.dtype, np.integer):
        raise ValueError(f"roi: expected integer vertex indices, got dtype {roi.dtype}")
    if roi.min() < 0 or roi.max() >= v:
        raise ValueError(f"roi: vertex indices must lie in [0, {v})")
    if np.unique(roi).size != roi.size:
        raise ValueError("roi: vertex indices must be distinct")
    for name, x in (("metric", metric), ("library", library), ("query", query)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: contains non-finite values")
    if not tau > 0:
        raise ValueError(f"tau: expected a value > 0, got {tau}")
    if library.shape[0] == 0:
        return SearchResult(np.zeros(0, np.int64), np.zeros(0, np.float32))
    energy = np.asarray(region_energy(jnp.asarray(metric[roi]), query, library))
    order = np.argsort(energy, kind="stable")
    order = order[energy[order] < tau]
    return SearchResult(order, energy[order])
