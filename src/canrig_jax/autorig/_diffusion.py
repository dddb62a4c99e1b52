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

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ..mesh import MeshOperators

METHODS = ("spectral", "implicit")


def _decayed_coefficients(features, times, operators):
    """exp(-lambda t) Phi^T M u as (k, N C) for (V, ..., C) features."""
    flat = features.reshape(features.shape[0], -1)
    coefficients = operators.eigenvectors.T @ (operators.mass[:, None] * flat)  # (k, N C)
    decay = jnp.exp(-operators.eigenvalues[:, None] * times[None, :])  # (k, C)
    k, c = decay.shape
    return (coefficients.reshape(k, -1, c) * decay[:, None, :]).reshape(k, -1)


def spectral_diffusion(
    features: Float[Array, "V *N C"], times: Float[Array, " C"], operators: MeshOperators
) -> Float[Array, "V *N C"]:
    """Phi exp(-lambda t) Phi^T M u for each channel (times >= 0, in squared mesh units).

    ``features`` may be (V, C) or (V, ..., C) (several feature sets, one matrix product)."""
    coefficients = _decayed_coefficients(features, times, operators)
    return (operators.eigenvectors @ coefficients).reshape(features.shape)


def spectral_diffusion_and_gradient(
    features: Float[Array, "V *N C"], times: Float[Array, " C"], operators: MeshOperators
) -> tuple[Float[Array, "V *N C"], Float[Array, "V *N C"], Float[Array, "V *N C"]]:
    """(u(t), grad_x u(t), grad_y u(t)) for spectral diffusion, from one set of spectral
    coefficients: u(t) = Phi c and G u(t) = (G Phi) c exactly (G linear), so the gradients
    are dense products with ``operators.eigenvector_gradients`` (no sparse gathers)."""
    coefficients = _decayed_coefficients(features, times, operators)
    diffused = (operators.eigenvectors @ coefficients).reshape(features.shape)
    g = operators.eigenvector_gradients
    grad_x = (g[..., 0] @ coefficients).reshape(features.shape)
    grad_y = (g[..., 1] @ coefficients).reshape(features.shape)
    return diffused, grad_x, grad_y


def implicit_diffusion(
    features: Float[Array, "V C"],
    times: Float[Array, " C"],
    operators: MeshOperators,
    *,
    tol: float = 1e-5,
    maxiter: int = 2000,
) -> Float[Array, "V C"]:
    """(M + t L)^{-1} M u for each channel, by preconditioned conjugate gradients.

    ``features`` may be (V, C) or (V, ..., C)."""
    column = (-1,) + (1,) * (features.ndim - 1)
    mask = operators.vertex_mask.reshape(column)
    mass = jnp.where(operators.vertex_mask > 0, operators.mass, 1.0).reshape(column)
    rhs = mask * operators.mass.reshape(column) * features
    diagonal = mass + times * operators.laplacian.diagonal(mass.shape[0]).reshape(column)

    def matvec(y):
        return mass * y + times * operators.laplacian(y)

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

    def __init__(
        self,
        width: int,
        method: str = "spectral",
        init_time: float = 0.0,
        *,
        key: PRNGKeyArray | None = None,
    ):
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        if width < 1:
            raise ValueError(f"width: expected a positive channel count, got {width}")
        self.times = jnp.full((width,), float(init_time), jnp.float32)
        self.method = method

    def __call__(
        self, features: Float[Array, "V *N C"], operators: MeshOperators
    ) -> Float[Array, "V *N C"]:
        times = jnp.abs(self.times)
        if self.method == "spectral":
            return spectral_diffusion(features, times, operators)
        return implicit_diffusion(features, times, operators)

    def with_gradient(
        self, features: Float[Array, "V *N C"], operators: MeshOperators
    ) -> tuple[Float[Array, "V *N C"], Float[Array, "V *N C"], Float[Array, "V *N C"]]:
        """(diffused, grad_x, grad_y) of the diffused features in the vertex frames."""
        if self.method == "spectral":
            return spectral_diffusion_and_gradient(features, jnp.abs(self.times), operators)
        diffused = self(features, operators)
        return diffused, operators.gradient_x(diffused), operators.gradient_y(diffused)
