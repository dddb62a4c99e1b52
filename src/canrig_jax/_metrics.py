"""Mesh distance metrics. ICT is in centimetres; errors are reported in millimetres."""

import numpy as np
from jaxtyping import ArrayLike, Float

CM_TO_MM = 10.0


def per_vertex_distance(
    a: Float[ArrayLike, "*batch 3"], b: Float[ArrayLike, "*batch 3"]
) -> Float[np.ndarray, "*batch"]:
    """(..., V) Euclidean distance between corresponding vertices of (..., V, 3) meshes."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.shape[-1] != 3:
        raise ValueError(f"a, b: expected equal shapes (..., V, 3), got {a.shape} and {b.shape}")
    return np.linalg.norm(a - b, axis=-1)


def distance_percentile_mm(
    a: Float[ArrayLike, "*batch 3"], b: Float[ArrayLike, "*batch 3"], q: float = 95.0
) -> float:
    """The q-th percentile of per-vertex distance (mm), pooled over all poses and vertices of
    meshes in centimetres."""
    return float(np.percentile(per_vertex_distance(a, b), q) * CM_TO_MM)
