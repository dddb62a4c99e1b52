"""Per-vertex input features and pooling over a mesh, from its ``MeshOperators``."""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_real, is_concrete
from ..mesh import MeshOperators


def heat_kernel_signature(
    operators: MeshOperators, times: Float[Array, " T"]
) -> Float[Array, "V T"]:
    """HKS (Sun, Ovsjanikov & Guibas 2009): sum_i exp(-lambda_i t) phi_i(x)^2 per time.

    Intrinsic, hence unchanged by rigid motions (DiffusionNet's rotation-invariant input).
    Concrete ``times`` must be finite and >= 0 (a negative time grows exponentially with the
    eigenvalue instead of smoothing): ValueError naming ``times`` otherwise.
    """
    if is_concrete(times):
        values = np.asarray(times)
        if values.ndim != 1 or values.size == 0:
            raise ValueError(f"times: expected a non-empty 1-D array, got shape {values.shape}")
        check_real("times", values)
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            raise ValueError(f"times: expected finite diffusion times >= 0, got min {values.min()}")
    decay = jnp.exp(-operators.eigenvalues[None, :] * jnp.asarray(times)[:, None])  # (T, k)
    return (operators.eigenvectors**2) @ decay.T


def hks_times(
    eigenvalues: Float[ArrayLike, " k"], n_times: int = 16
) -> Float[np.ndarray, " n_times"]:
    """Log-spaced times from 4 ln 10 / lambda_max to 4 ln 10 / lambda_min (non-zero
    eigenvalues), Sun et al.'s range."""
    values = np.asarray(eigenvalues)
    if not np.all(np.isfinite(values)):
        raise ValueError("eigenvalues: contains non-finite values")
    if isinstance(n_times, bool) or not isinstance(n_times, int | np.integer) or n_times < 1:
        raise ValueError(f"n_times: expected a positive integer, got {n_times!r}")
    nonzero = values[values > 0]
    if nonzero.size == 0:
        raise ValueError("eigenvalues: need at least one non-zero eigenvalue for HKS times")
    return np.geomspace(4 * np.log(10) / nonzero.max(), 4 * np.log(10) / nonzero.min(), n_times)


def mass_weighted_mean(
    features: Float[Array, "V C"], operators: MeshOperators
) -> Float[Array, " C"]:
    """sum_v m_v x_v / sum_v m_v: global average pooling by vertex area (padding and
    isolated vertices have zero mass, so they do not count)."""
    mass = operators.mass * operators.vertex_mask
    return (mass @ features) / jnp.sum(mass)
