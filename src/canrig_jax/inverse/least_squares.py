"""Closed-form baselines on the linear rig, clipped to the [0, 1] box."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


class Joshi(eqx.Module):
    """Joshi et al. 2006: pseudoinverse least squares w = B^+ (b - b0), clipped to [0, 1]."""

    def __call__(self, problem, offset, init, order=None, key=None):
        return jnp.clip(problem.pseudoinverse @ offset, 0.0, 1.0), None


class Cetinaslan(eqx.Module):
    """Çetinaslan & Orvalho 2020: (B^T B + 2 alpha I) w = B^T (b - b0), clipped to [0, 1]."""

    alpha: float = 0.0

    def __check_init__(self):
        if not self.alpha >= 0:
            raise ValueError(f"alpha: expected a non-negative regulariser, got {self.alpha}")

    def __call__(self, problem, offset, init, order=None, key=None):
        return ridge_weights(problem, offset, self.alpha), None


def ridge_weights(problem, offset, alpha):
    """(K,) clip((B^T B + 2 alpha I)^-1 B^T (b - b0), 0, 1); ``alpha`` may be traced."""
    k = problem.n_blendshapes
    system = problem.gram[:k, :k] + 2.0 * alpha * jnp.eye(k)
    weights = jnp.linalg.solve(system, problem.basis[:, :k].T @ offset)
    return jnp.clip(weights, 0.0, 1.0)
