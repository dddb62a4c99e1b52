"""Per-vertex colours for the viewer's ``COLOR_0`` channel (error maps)."""

import numpy as np
from jaxtyping import ArrayLike, Float

from .._checks import check_finite, check_real


def error_colors(error: Float[ArrayLike, " V"], vmax: float) -> Float[np.ndarray, "V 3"]:
    """(V, 3) linear RGB in [0, 1] of (V,) non-negative errors: white at 0, pure red at
    ``vmax`` and above (write with ``rig.export_animated_gltf(..., vertex_colors=)``)."""
    error = np.asarray(error)
    if error.ndim != 1 or error.size == 0:
        raise ValueError(f"error: expected a non-empty (V,) array, got shape {error.shape}")
    check_real("error", error)
    check_finite("error", error)
    if error.min() < 0:
        raise ValueError(f"error: expected non-negative errors, got a minimum of {error.min()}")
    if not np.isfinite(vmax) or vmax <= 0:
        raise ValueError(f"vmax: expected a positive error for full red, got {vmax}")
    fade = 1.0 - np.clip(error / vmax, 0.0, 1.0)
    return np.stack([np.ones_like(fade), fade, fade], axis=-1).astype(np.float32)
