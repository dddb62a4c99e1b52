"""Geodesic influence masks of CANRig handles (section 3.1 and appendix A).

Distances are shortest paths on the mesh's edge graph, each edge weighted by its 3D length
(``canrig_jax.mesh.edge_graph`` and ``weighted_geodesic_distance``, the geometry's one home,
re-exported here), so a handle on the upper lip reaches the lower lip only around the mouth
corner, never across the mouth gap. Appendix A's correlation prior scales
each edge by ``1 - |corr(v_i, v_j)|``: vertices that move together are close.

The mask of handle h on vertex v is (arrays are laid out vertices x handles, (V, H), the
layout the attention consumes)

    M_{h,v} = 0.5 (1 - tanh(gamma_h (d(h, v) - r_h)))

with radius r_h and falloff gamma_h per handle. ``influence_mask`` is a jnp function of
arrays, so radii and falloffs change per call without recompiling.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float32, Float64, Int

from .._checks import check_real, is_concrete
from ..mesh import edge_graph, mesh_edges, weighted_geodesic_distance

__all__ = [
    "CLAMP",
    "MIN_EDGE_FACTOR",
    "check_handle_parameters",
    "correlation_edge_factor",
    "edge_graph",
    "influence_mask",
    "mesh_edges",
    "weighted_geodesic_distance",
]

CLAMP = 1e-2
"""Influences below this are clamped to exactly 0 (section 3.2)."""

MIN_EDGE_FACTOR = 1e-3
"""Floor of the correlation-prior edge factor: csgraph drops zero-weight edges."""


def correlation_edge_factor(
    faces: Int[ArrayLike, "F 3"], shapes: Float[ArrayLike, "N V 3"]
) -> Float64[np.ndarray, " E"]:
    """(E,) appendix A's prior ``1 - |corr(v_i, v_j)|`` per edge of ``mesh_edges(faces)``.

    ``shapes`` (N, V, 3) are training shapes; the correlation of two vertices is the Pearson
    correlation of their displacement from the mean shape, pooled over the N shapes and 3
    coordinates. Floored at ``MIN_EDGE_FACTOR`` so every edge keeps a positive weight.
    """
    shapes = np.asarray(shapes)
    check_real("shapes", shapes)
    shapes = shapes.astype(np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or shapes.shape[0] < 2:
        raise ValueError(f"shapes: expected shape (N >= 2, V, 3), got {shapes.shape}")
    if not np.all(np.isfinite(shapes)):
        raise ValueError("shapes: contains non-finite values")
    edges = mesh_edges(faces)
    if edges.max() >= shapes.shape[1]:
        raise ValueError("faces: indices exceed the vertex count of shapes")
    centred = shapes - shapes.mean(axis=0)
    # (V, 3N): each vertex's displacement trajectory, centred per coordinate
    signal = centred.transpose(1, 0, 2).reshape(shapes.shape[1], -1)
    norm = np.linalg.norm(signal, axis=1)
    dot = np.einsum("ek,ek->e", signal[edges[:, 0]], signal[edges[:, 1]])
    denom = norm[edges[:, 0]] * norm[edges[:, 1]]
    corr = np.where(denom > 0, dot / np.where(denom > 0, denom, 1.0), 0.0)
    return np.maximum(1.0 - np.abs(corr), MIN_EDGE_FACTOR)


def influence_mask(
    distance: Float[ArrayLike, "*shape"],
    radius: Float[ArrayLike, "*#shape"],
    falloff: Float[ArrayLike, "*#shape"],
    clamp: float = 0.0,
) -> Float[Array, "*shape"]:
    """Influence M_{h,v} = 0.5 (1 - tanh(falloff_h (d_{h,v} - radius_h))) of each handle
    (last axis) on each vertex; values below ``clamp`` become exactly 0, infinite distances
    (unreachable, beyond a distance limit) give 0. jit/vmap/grad-safe.

    ``distance`` is (V, H) (or a layout's local form, e.g. (B, S, W)); ``radius`` and
    ``falloff`` (H,), or anything that broadcasts against ``distance`` (a scalar, (B, 1, W)).

    Concrete (non-traced) arguments are checked first: ValueError for a NaN or negative
    distance, or a radius or falloff that is not finite and > 0 (a negative one inverts the
    mask). Traced arguments are the caller's to check (``check_handle_parameters``).
    """
    _check_mask_inputs(distance, radius, falloff, clamp)
    distance = jnp.asarray(distance)
    radius = jnp.asarray(radius)
    falloff = jnp.asarray(falloff)
    finite = jnp.isfinite(distance)
    scaled = falloff * (jnp.where(finite, distance, 0.0) - radius)
    mask = jnp.where(finite, 0.5 * (1.0 - jnp.tanh(scaled)), 0.0)
    if clamp > 0.0:
        mask = jnp.where(mask < clamp, 0.0, mask)
    return mask


def check_handle_parameters(
    radius: float | Float[ArrayLike, " H"], falloff: float | Float[ArrayLike, " H"], n_handles: int
) -> tuple[Float32[np.ndarray, " H"], Float32[np.ndarray, " H"]]:
    """Validate radius and falloff (scalars or (H,)) and broadcast them to (H,) float32."""
    out = []
    for name, value in (("radius", radius), ("falloff", falloff)):
        arr = np.asarray(value)
        check_real(name, arr)
        arr = arr.astype(np.float32)
        if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n_handles):
            raise ValueError(f"{name}: expected a scalar or shape ({n_handles},), got {arr.shape}")
        if not np.all(np.isfinite(arr)) or not np.all(arr > 0):
            raise ValueError(f"{name}: expected finite values > 0, got min {arr.min()}")
        out.append(np.broadcast_to(arr, (n_handles,)).copy())
    return out[0], out[1]


def _check_mask_inputs(distance, radius, falloff, clamp) -> None:
    """The checks of ``influence_mask`` on its concrete (non-traced) arguments."""
    if is_concrete(distance):
        check_real("distance", distance)
        d = np.asarray(distance)
        if np.any(np.isnan(d)):
            raise ValueError("distance: contains NaN (unreachable vertices should be inf)")
        if np.any(d < 0):
            raise ValueError(f"distance: expected distances >= 0, got min {d.min()}")
    for name, value in (("radius", radius), ("falloff", falloff)):
        if is_concrete(value):
            check_real(name, value)
            v = np.asarray(value)
            if v.size and (not np.all(np.isfinite(v)) or not np.all(v > 0)):
                raise ValueError(f"{name}: expected finite values > 0, got min {v.min()}")
    if is_concrete(clamp) and not (np.isfinite(clamp) and 0 <= clamp < 1):
        raise ValueError(f"clamp: expected a value in [0, 1), got {clamp}")
