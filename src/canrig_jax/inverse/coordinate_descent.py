"""Coordinate descent of Racković et al. 2023 (Algorithm 1) and its linear and Seol variants.

QuarticCD updates one weight at a time in closed form: f is affine in w_i,
f(w) = f(w|w_i=0) + w_i phi_i, so with psi_i = f(w|w_i=0) - b (the rest of the rig minus the
target) the 1-D problem min_{0<=w_i<=u} 1/2||w_i phi_i + psi_i||^2 + alpha w_i has the solution

    w_i <- clip((-phi_i^T psi_i - alpha) / ||phi_i||^2, 0, u).

All inner products are taken in coefficient space (see ``problem.py``): phi_i = M g_i with
g_i = a(w|w_i=1) - a(w|w_i=0), so ||phi_i||^2 = g^T Q g and phi_i^T psi_i = g^T (Q a_rest - p).
g_i is non-zero only on the m columns that contain weight i, so each update is an m x P
product, independent of the vertex count.
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
    """1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig; ``offset`` = (b - b0).ravel().

    Computed in coefficient space, 1/2 (a^T Q a - 2 a^T M^T (b - b0) + ||b - b0||^2), which
    shares the projection M^T (b - b0) with the solvers instead of forming a second 3V-vector
    (float32: absolute error ~1e-7 ||b - b0||^2)."""
    return problem.objective(weights, problem.basis.T @ offset, offset @ offset, alpha)


STATIC_ORDERS = ("decreasing", "increasing", "random", "frame_correlation")
ORDERS = (*STATIC_ORDERS, "iteration_correlation", "gauss_southwell", "max_improvement")
"""Coordinate orders of Racković et al. section 4.4:

- ``decreasing`` / ``increasing``: by the blendshape norm ||b_i||, fixed for all passes;
- ``random``: a fresh random permutation each pass;
- ``frame_correlation``: by |b_i^T (b - b0)| / ||b_i||, the target's correlation with each
  blendshape, once per frame;
- ``iteration_correlation``: the same with the current residual, recomputed every pass;
- ``gauss_southwell``: each step updates the weight with the largest projected gradient;
- ``max_improvement``: each step makes the single coordinate update that lowers the objective
  most (K candidate updates per step).

Greedy orders make K updates per pass, possibly revisiting a weight."""


def check_order(order: str) -> None:
    if order not in ORDERS:
        raise ValueError(f"order: unknown coordinate order {order!r}; expected one of {ORDERS}")


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
        init: Float[Array, " K"],
        order: str = "decreasing",
        key: jax.Array | None = None,
    ):
        model = linear_part(problem) if self.linear else problem
        k, width = problem.n_blendshapes, model.gram.shape[0]
        # the full projection, sliced, so XLA shares it with ``solve``'s final objective
        projection = (problem.basis.T @ offset)[:width]
        offset_sq = offset @ offset
        alpha, upper = self.alpha, self.upper

        def derivative(weights, i):
            """(m,) d a / d w_i on the support of i: the product of the other weights of each
            combination (1 for column i itself); a(w) is affine in w_i with this slope."""
            extended = jnp.append(weights, jnp.ones((1,), weights.dtype))
            g = jnp.prod(extended[model.support_others[i]], axis=-1)
            return jnp.where(model.support_valid[i], g, 0.0)

        def line(weights, i):
            """Closed-form update of coordinate i: (new value, objective decrease).

            Only the columns that depend on w_i enter: with S = support_i and
            g = d a / d w_i (zero off S), ||phi_i||^2 = g_S^T Q[S, S] g_S and
            phi_i^T psi_i = g_S^T (Q[S, :] a(w|w_i=0) - p_S), an m x P product."""
            g = derivative(weights, i)
            rows = model.support_gram[i]  # (m, P) = Q[support_i, :]
            support = model.support[i]
            a_rest = model.coefficients(weights.at[i].set(0.0))
            curvature = g @ rows[:, support] @ g
            slope = g @ (rows @ a_rest - projection[support]) + alpha
            safe = curvature > 1e-12
            value = jnp.clip(-slope / jnp.where(safe, curvature, 1.0), 0.0, upper)
            value = jnp.where(safe, value, 0.0)
            old = weights[i]
            decrease = (old - value) * slope + 0.5 * (old**2 - value**2) * curvature
            return value, decrease

        def choose(weights):
            if order == "gauss_southwell":
                gradient = model.gram @ model.coefficients(weights) - projection
                slopes = jax.vmap(lambda i: derivative(weights, i) @ gradient[model.support[i]])(
                    jnp.arange(k)
                )
                slopes = slopes + alpha
                stuck = ((weights <= 0) & (slopes > 0)) | ((weights >= upper) & (slopes < 0))
                return jnp.argmax(jnp.where(stuck, 0.0, jnp.abs(slopes)))
            _, decrease = jax.vmap(line, (None, 0))(weights, jnp.arange(k))
            return jnp.argmax(decrease)

        def step(weights, i):
            if order in ("gauss_southwell", "max_improvement"):
                i = choose(weights)
            weights = weights.at[i].set(line(weights, i)[0])
            if not self.trace:
                return weights, None
            # in vertex space: the coefficient-space form loses ~1e-7 ||b - b0||^2 to
            # cancellation, more than late coordinate updates gain
            residual = model.basis @ model.coefficients(weights) - offset
            return weights, 0.5 * residual @ residual + alpha * weights.sum()

        def sweep(weights, sequence):
            if order == "iteration_correlation":
                a = model.coefficients(weights)
                correlation = model.gram[:k] @ a - projection[:k]  # B^T (f(w) - b)
                sequence = jnp.argsort(-jnp.abs(correlation) / problem.blendshape_norms)
            weights, per_coordinate = jax.lax.scan(step, weights, sequence.astype(jnp.int32))
            if self.trace:
                return weights, per_coordinate
            return weights, model.objective(weights, projection, offset_sq, alpha)

        sequences = static_order(problem, order, self.passes, offset, key)
        weights, history = jax.lax.scan(sweep, init, sequences)
        return weights, history.reshape(-1)


def linear_part(problem: InverseProblem) -> InverseProblem:
    """The problem of the rig without correctives (its first K columns)."""
    k = problem.n_blendshapes
    return eqx.tree_at(
        lambda p: (
            p.basis,
            p.gram,
            p.combinations,
            p.support,
            p.support_others,
            p.support_valid,
            p.support_gram,
        ),
        problem,
        (
            problem.basis[:, :k],
            problem.gram[:k, :k],
            (),
            problem.support[:, :1],
            problem.support_others[:, :1],
            problem.support_valid[:, :1],
            problem.support_gram[:, :1, :k],
        ),
    )


def static_order(
    problem: InverseProblem,
    order: str,
    passes: int,
    offset: Float[Array, " N"],
    key: jax.Array | None = None,
) -> Int[Array, "T K"]:
    """(passes, K) int32 coordinate sequence of each pass (placeholder rows for the orders
    decided during the solve)."""
    check_order(order)
    k = problem.n_blendshapes
    if order == "random":
        keys = jax.random.split(jax.random.key(0) if key is None else key, passes)
        return jax.vmap(lambda kk: jax.random.permutation(kk, k))(keys).astype(jnp.int32)
    if order == "frame_correlation":
        score = jnp.abs(problem.basis[:, :k].T @ offset) / problem.blendshape_norms
    elif order == "increasing":
        score = -problem.blendshape_norms
    else:
        score = problem.blendshape_norms
    return jnp.tile(jnp.argsort(-score).astype(jnp.int32), (passes, 1))


class LinearCD(QuarticCD):
    """QuarticCD on the rig without correctives (the rig's linear part)."""

    linear: bool = eqx.field(static=True, default=True)


class Seol(eqx.Module):
    """Seol et al. 2011: one pass of residual subtraction on the linear rig, no L1 and no upper
    bound, w_i = max(0, b_i^T r / ||b_i||^2), r <- r - w_i b_i; computed in vertex space,
    independently of the coefficient-space coordinate descent."""

    def __call__(self, problem, offset, init, order="decreasing", key=None):
        shapes = problem.basis[:, : problem.n_blendshapes]
        sequence = static_order(problem, order, 1, offset, key)[0]

        def step(carry, i):
            weights, residual = carry
            column = shapes[:, i]
            value = jnp.maximum(column @ residual / (column @ column), 0.0)
            return (weights.at[i].set(value), residual - value * column), None

        (weights, _), _ = jax.lax.scan(step, (jnp.zeros_like(init), offset), sequence)
        return weights, None
