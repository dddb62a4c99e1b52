"""Projected Gauss-Newton on the whole box: the inverse rig's minimum in a few joint steps.

On [0, u]^K the L1 term alpha 1^T w is linear, so Racković et al.'s objective

    E(w) = 1/2 ||f(w) - b||^2 + alpha 1^T w = 1/2 a^T Q a - a^T p + 1/2 ||b - b0||^2 + alpha 1^T w

(coefficient space, see ``_problem.py``) is smooth on the box, and a projected Newton method
(Bertsekas 1982) reaches its minimum in a handful of joint steps where coordinate descent
needs ~10 passes of K sequential updates. Each iteration:

1. the gradient grad = G (Q a - p) + alpha, with G = d a / d w (K x P, the product rule
   over each combination);
2. the epsilon-active set: weights within eps of a bound whose gradient pushes them out of
   the box (eps = min(1e-3 u, ||w - clip(w - grad)||)); they stay where they are, which is
   what keeps the L1 term's exact zeros (the solution is as sparse as coordinate descent's);
3. on the free weights, the Gauss-Newton system (G Q G^T)_FF d_F = -grad_F (Cholesky with a
   1e-6 relative ridge; the full rig's Hessian is not convex in general, its Gauss-Newton
   part is positive semi-definite);
4. a projected line search over ``line_steps`` step lengths 1, 1/2, 1/4, ... evaluated
   together, taking the lowest objective if it is lower than the current one.

It stops when an iteration lowers E by less than ``tol`` relative to E. Objective changes are
computed as differences in coefficient space (1/2 (a' - a)^T Q (a' + a) - (a' - a)^T p + ...),
so the float32 cancellation of the absolute form (against ||b - b0||^2) does not limit the
tolerance.

Cost per iteration: one (K, P) x (P, P) product for G Q (a dense matmul: on ict-quartic
53 x 620 x 620, ~0.4 ms on this project's CPU), the rest is K x K or P-sized. On ict-quartic
with the Live Link take it needs ~7 iterations from zero and ~4.7 warm-started
(``benchmarks/bench_inverse.py``).
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .._linalg import spd_solve
from ._base import (
    AbstractInverseMethod,
    Iterate,
    check_alpha,
    check_count,
    check_tol,
    check_upper,
)
from ._coordinate_descent import _one_frame_or_batch
from ._problem import InverseProblem

NewtonCarry = tuple[Float[Array, " K"], Float[Array, "K K"], Bool[Array, ""]]
"""What ``QuarticNewton`` hands from one frame of a ``Stream`` to the next: (the weights at
which its Gauss-Newton matrix was computed, that (K, K) matrix, whether it was carried from a
previous solve rather than exact at the start)."""


class QuarticNewton(AbstractInverseMethod):
    """Projected Gauss-Newton on the full rig's L1-penalised objective over [0, ``upper``]^K
    (see the module docstring): the same minimum as converged ``QuarticCD`` in a few joint
    steps, with the same exact zeros.

    Attributes:
        alpha: L1 weight (>= 0), in squared rig units like the data term (cm^2 for ICT).
        iterations: cap on the Newton iterations.
        tol: stop when an iteration lowers the objective by less than ``tol`` relative to its
            value (0 runs all ``iterations``).
        line_steps: step lengths tried per iteration (1, 1/2, ..., 2^-(line_steps - 1)).
        upper: upper bound of the box (1 in the paper; ``jnp.inf`` for none), or (K,)
            per-weight bounds >= 0 (a bound of 0 holds its weight at exactly 0; how
            ``Constrained`` keeps one of a mutually exclusive pair off).
        refresh: one frame at a time, the Gauss-Newton matrix G Q G^T (the one K x P x P
            product of an iteration, most of its cost) is recomputed every ``refresh``
            iterations and reused in between (a chord step: still a descent direction, the
            line search still only accepts decreases); an iteration that gains less than
            ``tol`` on a reused matrix recomputes it before the solve may stop, so the
            stopping test is always passed on a fresh one. 1 (default) recomputes it every
            iteration. Under ``vmap`` (a take) it is recomputed every iteration whatever
            ``refresh`` is (the batch shares one branch).
    """

    alpha: float = 0.0
    iterations: int = eqx.field(static=True, default=50)
    tol: float = 1e-5
    line_steps: int = eqx.field(static=True, default=6)
    upper: float | Float[ArrayLike, " K"] = 1.0
    refresh: int = eqx.field(static=True, default=1)
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        check_alpha(self.alpha)
        check_count("iterations", self.iterations)
        check_count("line_steps", self.line_steps)
        check_count("refresh", self.refresh)
        check_upper(self.upper, per_weight=True)
        check_tol(self.tol)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        return self.step(problem, offset, init, key, self.initial_carry(problem))[0]

    def initial_carry(self, problem: InverseProblem) -> NewtonCarry:
        """(point, Gauss-Newton matrix at it, carried): at w = 0 every product of two or more
        weights has a zero factor, so G = [I 0] and the matrix is the linear Gram block; a
        solve from zero starts with it for free."""
        k = problem.n_blendshapes
        return jnp.zeros(k, problem.gram.dtype), problem.gram[:k, :k], jnp.asarray(False)

    def step(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
        carry: NewtonCarry,
    ) -> tuple[Iterate, NewtonCarry]:
        """The solve from ``init`` with the Gauss-Newton matrix of ``carry`` (exact where
        ``init`` is its point; from a previous frame's solve it is one iteration old, so it
        counts as reused); returns the matrix last computed for the next frame."""
        gram, alpha, upper = problem.gram, self.alpha, self.upper
        if jnp.ndim(upper) == 1 and jnp.shape(upper) != (problem.n_blendshapes,):
            k = problem.n_blendshapes
            raise ValueError(f"upper: expected ({k},) per-weight bounds, got {jnp.shape(upper)}")
        projection = problem.projection(offset)
        lengths = 0.5 ** jnp.arange(self.line_steps, dtype=gram.dtype)

        def iteration(state):
            n, weights, value, gain, history, hessian, at, age, _ = state
            a = problem.coefficients(weights)
            residual = gram @ a - projection  # Q a - p
            jacobian = problem.jacobian(weights)
            grad = jacobian @ residual + alpha
            stale = (age >= self.refresh) | (gain <= self.tol * jnp.abs(value))
            stale = _one_frame_or_batch(stale, jnp.asarray(True))  # a batch: every iteration
            hessian = jax.lax.cond(stale, lambda: (jacobian @ gram) @ jacobian.T, lambda: hessian)
            at = jnp.where(stale, weights, at)
            age = jnp.where(stale, 1, age + 1)
            eps = jnp.minimum(
                1e-3 * upper, jnp.linalg.norm(weights - jnp.clip(weights - grad, 0.0, upper))
            )
            held = ((weights <= eps) & (grad > 0)) | ((weights >= upper - eps) & (grad < 0))
            free = ~held
            ridge = 1e-6 * jnp.max(jnp.abs(jnp.diag(hessian)))
            system = jnp.where(free[:, None] & free[None, :], hessian, 0.0)
            system = system + jnp.diag(jnp.where(free, ridge, 1.0))
            step = spd_solve(system, -jnp.where(free, grad, 0.0))
            step = jnp.where(free & jnp.isfinite(step), step, 0.0)
            trials = jnp.clip(weights + lengths[:, None] * step, 0.0, upper)  # (L, K)
            # E(trial) - E(w) in coefficient space: no cancellation against ||b - b0||^2
            change = jax.vmap(problem.coefficients)(trials) - a
            decrease = (
                change @ residual
                + 0.5 * jnp.sum((change @ gram) * change, axis=1)
                + alpha * (trials - weights).sum(axis=1)
            )
            best = jnp.argmin(decrease)
            better = decrease[best] < 0
            weights = jnp.where(better, trials[best], weights)
            gain = jnp.where(better, -decrease[best], 0.0)
            # no length lowered E although the model predicts a decrease above the
            # tolerance (1/2 g^T H^-1 g on the free weights): stalled, not converged
            stalled = ~better & (-0.5 * (grad @ step) > self.tol * jnp.abs(value))
            value = value - gain
            history = history.at[n].set(value)
            return n + 1, weights, value, gain, history, hessian, at, age, stalled

        def keep_going(state):
            n, _, value, gain, _, _, _, age, _ = state
            small = gain <= self.tol * jnp.abs(value)
            return (n < self.iterations) & ((n == 0) | ~small | (age > 1))

        value0 = problem.objective(init, projection, offset @ offset, alpha)
        history0 = jnp.zeros(self.iterations, gram.dtype)
        at0, hessian0, carried = carry
        age0 = jnp.where(jnp.all(init == at0), 0, jnp.where(carried, 1, self.refresh))
        gain0 = jnp.asarray(jnp.inf, gram.dtype)
        state = (jnp.asarray(0), init, value0, gain0, history0, hessian0, at0, age0, False)
        n, weights, value, gain, history, hessian, at, age, stalled = jax.lax.while_loop(
            keep_going, iteration, state
        )
        history = jnp.where(jnp.arange(self.iterations) < n, history, value)
        converged = (gain <= self.tol * jnp.abs(value)) & (age == 1) & ~stalled
        result = optx.RESULTS.where(
            converged,
            optx.RESULTS.successful,
            optx.RESULTS.where(stalled, optx.RESULTS.stagnation, optx.RESULTS.max_steps_reached),
        )
        iterate = Iterate(weights, history, n, converged, result)
        return iterate, (at, hessian, jnp.asarray(True))
