"""LMMM (Racković et al. 2022): majorisation-minimisation for the rig with pair correctives.

Around the current weights w, with residual p = f(w) - b and Jacobian q = df/dw, the pairwise
rig is exactly f(w + v) = f(w) + q v + D(v), D(v)_k = v^T H_k v. The objective
E = 1/2 ||f - b||^2 + alpha 1^T w is bounded above by a separable quartic in the increment:

    E(w + v) <= E(w) + sum_i [(q^T p + alpha)_i v_i + c2 v_i^2 + c4 v_i^4],

using 1/2||q v||^2 <= 1/2 ||q||^2 ||v||^2; p^T D(v) <= (sum_{p_k>0} p_k lambda_max(H_k) +
sum_{p_k<0} p_k lambda_min(H_k)) ||v||^2 (the residual's sign split); (q v)^T D(v) <=
1/2 ||q v||^2 + 1/2 ||D(v)||^2; ||D(v)||^2 <= sum_k ||H_k||^2 ||v||^4 <= K sum_k ||H_k||^2
sum_i v_i^4. Hence c2 = ||q||^2 + sign-split term (kept >= 0) and c4 = K sum_k ||H_k||^2.
Each 1-D quartic is convex, its derivative a cubic with one real root, so the minimiser on the
feasible interval [-w_i, 1 - w_i] is that root clipped to the interval. Triplets and quads
are ignored by the method (metrics still use the full rig). Warm-started from Cetinaslan.

On a rig without pair correctives the quartic coefficient vanishes (c4 = 0) and the step is
the quadratic majoriser's, v = -linear / (2 c2): no cubic is solved (Cardano's formula with
c4 -> 0 overflows float32, which used to return NaN for every frame of a linear rig).
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._linalg import eigvalsh
from ._base import (
    AbstractInverseMethod,
    Iterate,
    check_alpha,
    check_count,
    check_tol,
    check_upper,
)
from ._least_squares import ridge_weights
from ._problem import InverseProblem


def _increasing_cubic_root(a, c2, c4):
    """Real root of a + 2 c2 v + 4 c4 v^3 (c2 >= 0, c4 >= 0, not both 0).

    Where the cubic term is negligible (c4 <= 1e-7 c2, the rig has no pair correctives) the
    linear root -a / (2 c2); otherwise Cardano's formula, then Newton polish."""
    quadratic = c4 <= 1e-7 * c2
    c4_safe = jnp.where(quadratic, 1.0, c4)
    p = c2 / (2.0 * c4_safe)
    q = a / (4.0 * c4_safe)
    disc = jnp.sqrt(q**2 / 4.0 + p**3 / 27.0)
    v = jnp.cbrt(-q / 2.0 + disc) + jnp.cbrt(-q / 2.0 - disc)
    for _ in range(2):
        v = v - (a + 2 * c2 * v + 4 * c4 * v**3) / (2 * c2 + 12 * c4 * v**2 + 1e-30)
    linear_root = -a / jnp.where(c2 > 0, 2.0 * c2, 1.0)
    return jnp.where(quadratic, linear_root, v)


class LMMM(AbstractInverseMethod):
    """Majorisation-minimisation on the pairwise rig.

    Iterates until an iteration lowers the pairwise objective by less than ``tol`` relative
    to its value (the test of converged ``QuarticCD`` and ``QuarticNewton``), at most
    ``iterations`` times; ``Solution.result`` is ``successful`` when the test held and
    ``max_steps_reached`` when the cap came first. The decrease is computed as a difference
    in coefficient space, so float32 cancellation against ||b - b0||^2 does not hide it.

    Attributes:
        alpha: L1 weight (>= 0).
        iterations: cap on the MM iterations (each lowers the pairwise objective).
        tol: relative decrease per iteration below which it stops (0: only a stalled
            iteration stops it before the cap).
        upper: box upper bound.
    """

    alpha: float = 0.0
    iterations: int = eqx.field(static=True, default=200)
    tol: float = 1e-6
    upper: float = 1.0
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        check_alpha(self.alpha)
        check_count("iterations", self.iterations)
        check_upper(self.upper)
        check_tol(self.tol)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        k = problem.n_blendshapes
        # tables are sorted by order, so the pair columns follow the K blendshape columns
        pairs = tuple(c for c in problem.combinations if c.shape[1] == 2)
        width = k + sum(c.shape[0] for c in pairs)
        model = eqx.tree_at(
            lambda p: (p.columns, p.gram, p.combinations),
            problem,
            (problem.columns[:width], problem.gram[:width, :width], pairs),
        )
        projection = problem.projection(offset)[:width]
        offset_sq = offset @ offset
        bounds = problem.pair_hessian_bounds
        c4 = k * jnp.sum(bounds[:, 2] ** 2)
        eye = jnp.eye(k, dtype=offset.dtype)

        def iteration(state):
            n, weights, _, _, history = state
            a = model.coefficients(weights)
            low = jax.vmap(model.coefficients)(weights * (1 - eye))
            high = jax.vmap(model.coefficients)(weights * (1 - eye) + eye)
            g = high - low  # (K, P): q = M g^T
            gradient = model.gram @ a - projection  # Q a - p
            linear = g @ gradient + self.alpha
            sigma_sq = eigvalsh(g @ model.gram @ g.T)[-1]
            residual = a @ model.columns - offset
            split = jnp.sum(
                jnp.maximum(residual, 0) * bounds[:, 1] + jnp.minimum(residual, 0) * bounds[:, 0]
            )
            c2 = jnp.maximum(sigma_sq + split, 0.0)
            root = _increasing_cubic_root(linear, c2, c4)
            step = jnp.clip(root, -weights, self.upper - weights)
            step = jnp.where(jnp.isnan(step), 0.0, step)
            new = weights + step
            # E(new) - E(w) in coefficient space: no cancellation against ||b - b0||^2
            change = model.coefficients(new) - a
            gain = -(
                change @ gradient + 0.5 * change @ model.gram @ change + self.alpha * step.sum()
            )
            value = model.objective(new, projection, offset_sq, self.alpha)
            return n + 1, new, value, gain, history.at[n].set(value)

        def keep_going(state):
            n, _, value, gain, _ = state
            return (n < self.iterations) & ((n == 0) | (gain > self.tol * jnp.abs(value)))

        start = jnp.clip(ridge_weights(problem, offset, self.alpha), 0.0, self.upper)
        value0 = model.objective(start, projection, offset_sq, self.alpha)
        history0 = jnp.zeros(self.iterations, offset.dtype)
        state = (jnp.asarray(0), start, value0, jnp.asarray(jnp.inf, offset.dtype), history0)
        n, weights, value, gain, history = jax.lax.while_loop(keep_going, iteration, state)
        history = jnp.where(jnp.arange(self.iterations) < n, history, value)
        converged = gain <= self.tol * jnp.abs(value)
        return Iterate(weights, history, n, converged)
