"""Coordinate descent of Racković et al. 2023 (Algorithm 1) and its linear and Seol variants.

QuarticCD updates one weight at a time in closed form: f is affine in w_i,
f(w) = f(w|w_i=0) + w_i phi_i, so with psi_i = f(w|w_i=0) - b (the rest of the rig minus the
target) the 1-D problem min_{0<=w_i<=u} 1/2||w_i phi_i + psi_i||^2 + alpha w_i has the solution

    w_i <- clip((-phi_i^T psi_i - alpha) / ||phi_i||^2, 0, u).

All inner products are taken in coefficient space (see ``problem.py``): phi_i = M g_i with
g_i = a(w|w_i=1) - a(w|w_i=0), so ||phi_i||^2 = g^T Q g and phi_i^T psi_i = g^T (Q a_rest - p),
a P-vector computation per coordinate, independent of the vertex count.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .problem import InverseProblem


def _check(alpha, passes, upper):
    if not alpha >= 0:
        raise ValueError(f"alpha: expected a non-negative L1 weight, got {alpha}")
    if not (isinstance(passes, int) and passes >= 1):
        raise ValueError(f"passes: expected an integer >= 1, got {passes}")
    if not upper > 0:
        raise ValueError(f"upper: expected a positive upper bound, got {upper}")


def objective(
    problem: InverseProblem,
    weights: Float[Array, " K"],
    offset: Float[Array, " N"],
    alpha: float,
) -> Float[Array, ""]:
    """1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig; ``offset`` = (b - b0).ravel()."""
    residual = problem.basis @ problem.coefficients(weights) - offset
    return 0.5 * residual @ residual + alpha * weights.sum()


def _gram_objective(model, weights, projection, offset_sq, alpha):
    a = model.coefficients(weights)
    return 0.5 * (a @ model.gram @ a - 2.0 * a @ projection + offset_sq) + alpha * weights.sum()


class QuarticCD(eqx.Module):
    """Algorithm 1: coordinate descent on the rig with all its correctives.

    Attributes:
        alpha: L1 weight (>= 0), in cm^2 like the data term.
        passes: sweeps over all K weights.
        upper: upper bound of the box (1 in the paper; ``jnp.inf`` for none).
        trace: record the objective after every coordinate update, not only every pass.
    """

    alpha: float = 0.0
    passes: int = eqx.field(static=True, default=5)
    upper: float = 1.0
    trace: bool = eqx.field(static=True, default=False)
    linear: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        _check(self.alpha, self.passes, self.upper)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        order: Int[Array, "T K"],
        init: Float[Array, " K"],
    ):
        k = problem.n_blendshapes
        model = problem
        if self.linear:
            model = eqx.tree_at(
                lambda p: (p.basis, p.gram, p.combinations),
                problem,
                (problem.basis[:, :k], problem.gram[:k, :k], ()),
            )
        projection = model.basis.T @ offset
        offset_sq = offset @ offset

        def step(weights, i):
            low, high = weights.at[i].set(0.0), weights.at[i].set(1.0)
            a_rest = model.coefficients(low)
            g = model.coefficients(high) - a_rest
            qg = model.gram @ g
            curvature = g @ qg
            slope = qg @ a_rest - g @ projection
            safe = curvature > 1e-12
            value = jnp.clip((-slope - self.alpha) / jnp.where(safe, curvature, 1.0), 0, self.upper)
            weights = weights.at[i].set(jnp.where(safe, value, 0.0))
            if not self.trace:
                return weights, None
            return weights, _gram_objective(model, weights, projection, offset_sq, self.alpha)

        def sweep(weights, sequence):
            weights, per_coordinate = jax.lax.scan(step, weights, sequence)
            if self.trace:
                return weights, per_coordinate
            return weights, _gram_objective(model, weights, projection, offset_sq, self.alpha)

        weights, history = jax.lax.scan(sweep, init, order[: self.passes])
        return weights, history.reshape(-1)


class LinearCD(QuarticCD):
    """QuarticCD on the rig without correctives (the rig's linear part)."""

    linear: bool = eqx.field(static=True, default=True)


class Seol(eqx.Module):
    """Seol et al. 2011: one pass of residual subtraction on the linear rig, no L1 and no upper
    bound, w_i = max(0, b_i^T r / ||b_i||^2), r <- r - w_i b_i; computed in vertex space,
    independently of the coefficient-space coordinate descent."""

    def __call__(self, problem, offset, order, init):
        shapes = problem.basis[:, : problem.n_blendshapes]

        def step(carry, i):
            weights, residual = carry
            column = shapes[:, i]
            value = jnp.maximum(column @ residual / (column @ column), 0.0)
            return (weights.at[i].set(value), residual - value * column), None

        (weights, _), _ = jax.lax.scan(step, (jnp.zeros_like(init), offset), order[0])
        return weights, None
