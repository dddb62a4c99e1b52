"""Heat diffusion on a mesh, the operator DiffusionNet learns a time for.

Diffusing u for time t solves du/dt = -M^{-1} L u. Two discretisations (Sharp et al. 2022):

* spectral: u(t) = Phi exp(-Lambda t) Phi^T M u, with the truncated M-orthonormal eigenbasis
  (exact with the full basis, a low-pass approximation with k modes);
* implicit: one backward-Euler step, u(t) = (M + t L)^{-1} M u (RigAnyFace eq. (1)), solved
  here by Jacobi-preconditioned conjugate gradients (``jax.scipy.sparse.linalg.cg``, whose
  derivatives are implicit: no unrolled iterations are stored).

Both take (V, C) features and one time per channel (C,), and are jit-, vmap- and grad-safe.
Vertices with ``vertex_mask`` 0 (padding, isolated) stay at zero and do not couple to others.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..mesh.operators import MeshOperators

METHODS = ("spectral", "implicit")


def spectral_diffusion(
    features: Float[Array, "V C"], times: Float[Array, " C"], operators: MeshOperators
) -> Float[Array, "V C"]:
    """Phi exp(-lambda t) Phi^T M u for each channel (times >= 0, in squared mesh units)."""
    coefficients = operators.eigenvectors.T @ (operators.mass[:, None] * features)  # (k, C)
    decay = jnp.exp(-operators.eigenvalues[:, None] * times[None, :])
    return operators.eigenvectors @ (decay * coefficients)


def implicit_diffusion(
    features: Float[Array, "V C"],
    times: Float[Array, " C"],
    operators: MeshOperators,
    *,
    tol: float = 1e-5,
    maxiter: int = 2000,
) -> Float[Array, "V C"]:
    """(M + t L)^{-1} M u for each channel, by preconditioned conjugate gradients."""
    mask = operators.vertex_mask[:, None]
    mass = jnp.where(operators.vertex_mask > 0, operators.mass, 1.0)[:, None]
    rhs = mask * operators.mass[:, None] * features
    diagonal = mass + times[None, :] * operators.laplacian.diagonal(mass.shape[0])[:, None]

    def matvec(y):
        return mass * y + times[None, :] * operators.laplacian(y)

    solution, _ = jax.scipy.sparse.linalg.cg(
        matvec, rhs, x0=features * mask, tol=tol, maxiter=maxiter, M=lambda r: r / diagonal
    )
    return solution * mask


class LearnedDiffusion(eqx.Module):
    """Diffusion with one learned time per channel (DiffusionNet's learned diffusion layer).

    The effective time is |times| (never negative, never stuck at a clamp).

    Args:
        width: channels.
        method: "spectral" or "implicit".
        init_time: initial time of every channel (squared mesh units; DiffusionNet uses 0 on
            meshes scaled to unit size).
        key: unused (the layer's initialisation is deterministic); keyword-only for symmetry.
    """

    times: Float[Array, " C"]
    method: str = eqx.field(static=True)

    def __init__(self, width: int, method: str = "spectral", init_time: float = 0.0, *, key=None):
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        if width < 1:
            raise ValueError(f"width: expected a positive channel count, got {width}")
        self.times = jnp.full((width,), float(init_time), jnp.float32)
        self.method = method

    def __call__(
        self, features: Float[Array, "V C"], operators: MeshOperators
    ) -> Float[Array, "V C"]:
        times = jnp.abs(self.times)
        if self.method == "spectral":
            return spectral_diffusion(features, times, operators)
        return implicit_diffusion(features, times, operators)
