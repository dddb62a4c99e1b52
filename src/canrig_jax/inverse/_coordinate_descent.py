"""Coordinate descent of Racković et al. 2023 (Algorithm 1), its linear variant and Seol.

QuarticCD updates one weight at a time in closed form: f is affine in w_i,
f(w) = f(w|w_i=0) + w_i phi_i, so with psi_i = f(w|w_i=0) - b (the rest of the rig minus the
target) the 1-D problem min_{0<=w_i<=u} 1/2||w_i phi_i + psi_i||^2 + alpha w_i has the solution

    w_i <- clip((-phi_i^T psi_i - alpha) / ||phi_i||^2, 0, u).

All inner products are taken in coefficient space (see ``_problem.py``): phi_i = M g_i with
g_i = a(w|w_i=1) - a(w|w_i=0), so ||phi_i||^2 = g^T Q g and phi_i^T psi_i = g^T (c - w_i Q g)
on the support S_i of g, where c = Q a(w) - p is the gradient of the data term in
coefficient space. c is kept up to date: changing w_i by d changes a by d g on S_i only, so
c <- c + d Q[:, S_i] g, an m x P product (m = |S_i|), independent of the vertex count. c is
recomputed from scratch once per pass (P x P), so float32 round-off does not accumulate.

Two additions to Algorithm 1, both optional fields:

- **a stopping rule**: with ``tol > 0``, passes stop once the objective's relative decrease
  over a pass falls below ``tol`` (``passes`` is then a cap); ``Solution.stats`` reports the
  passes taken and whether the tolerance was met.
- **an active-set Newton step** (``newton=True``) after each pass: on the free weights
  F = {0 < w_i < u} (the current support), one Gauss-Newton step of the full (multilinear)
  rig, H_FF d_F = -grad_F with H = G^T Q G (G = d a / d w), projected onto the box and kept
  only if it lowers the objective; the step is shortened so that no weight leaves the box
  (the first to reach a bound stops on it). Weights at 0 stay at 0, so the step keeps coordinate
  descent's sparsity; the next pass of coordinate descent adds or removes weights from the
  support. It costs about one pass (the K x m x P product Q G) plus a K x K Cholesky solve
  (``lineax``).

One frame at a time (``solve``, ``Stream``), work that cannot change the result is skipped:
an update that leaves its weight where it was (most often one held at 0 by the L1 term) does
not read its m x P block of Q, the Newton step forms the rows of Q G for the free weights
only, and it evaluates one trial instead of two when no free weight reaches a bound (on
ict-quartic, one-frame CPU time per Newton step -23 to -32 %, per pass -1 to -8 %, under
load). Under vmap the frames would need different branches, which JAX turns into computing
every branch and selecting (and XLA then loses the one matrix product over the frames):
``_one_frame_or_batch`` gives the batch the branch every frame needs instead, so a take
runs as before.
"""

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from equinox import AbstractVar
from jax.custom_batching import custom_vmap
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .._linalg import spd_solve
from ._base import (
    AbstractInverseMethod,
    Iterate,
    check_alpha,
    check_count,
    check_tol,
    check_upper,
)
from ._problem import InverseProblem

STATIC_ORDERS = ("decreasing", "increasing", "random", "frame_correlation")
ORDERS = (*STATIC_ORDERS, "iteration_correlation", "gauss_southwell", "max_improvement")
"""Coordinate orders of Racković et al. section 4.4:

- ``decreasing`` / ``increasing``: by the blendshape norm ||b_i||, fixed for all passes;
- ``random``: a fresh random permutation each pass, from the frame's own key;
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


def objective(
    problem: InverseProblem,
    weights: Float[ArrayLike, " K"],
    offset: Float[ArrayLike, " N"],
    alpha: float | Float[Array, ""],
) -> Float[Array, ""]:
    """1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig; ``offset`` = (b - b0).ravel().

    Computed in coefficient space, 1/2 (a^T Q a - 2 a^T M^T (b - b0) + ||b - b0||^2), which
    shares the projection M^T (b - b0) with the solvers instead of forming a second 3V-vector
    (float32: absolute error ~1e-7 ||b - b0||^2)."""
    weights, offset = jnp.asarray(weights), jnp.asarray(offset)
    return problem.objective(weights, problem.projection(offset), offset @ offset, alpha)


@custom_vmap
def _one_frame_or_batch(one_frame, batch):
    """``one_frame`` (a branch index or predicate that depends on the frame); under vmap,
    ``batch`` (one that holds for every frame), so that the ``switch``/``cond`` it drives
    stays a branch instead of running every branch and selecting (which also kept XLA from
    one matrix product over the frames: the batched solve was 2.7x slower)."""
    return one_frame


@_one_frame_or_batch.def_vmap
def _one_frame_or_batch_rule(axis_size, in_batched, one_frame, batch):
    if in_batched[1]:
        raise ValueError("batch: expected the same branch index for every frame")
    if not in_batched[0]:
        return one_frame, False
    return batch, False


class AbstractCoordinateDescent(AbstractInverseMethod):
    """Algorithm 1 on some part of the rig (``rig_part``), with the stopping rule and the
    active-set Newton step described in the module docstring.

    Attributes:
        alpha: L1 weight (>= 0), in squared rig units like the data term (cm^2 for ICT).
        passes: passes over all K weights; a cap when ``tol > 0``.
        tol: stop when a pass lowers the objective by less than ``tol`` relative to its
            value; 0 runs exactly ``passes`` passes (the paper's protocol).
        order: coordinate order, one of ``ORDERS``.
        newton: take the active-set Newton step after each pass.
        upper: upper bound of the box (1 in the paper; ``jnp.inf`` for none).
        trace: record the objective (in vertex space) after every coordinate update instead
            of once per pass; runs all ``passes`` (no early stop).
    """

    passes: AbstractVar[int]
    tol: AbstractVar[float]
    order: AbstractVar[str]
    newton: AbstractVar[bool]
    trace: AbstractVar[bool]
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        check_alpha(self.alpha)
        check_count("passes", self.passes)
        check_upper(self.upper)
        check_order(self.order)
        check_tol(self.tol)

    @abc.abstractmethod
    def rig_part(self, problem: InverseProblem) -> InverseProblem:
        """The problem of the rig the method assumes (all of it, or its linear part)."""

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        """Passes of coordinate descent from ``init`` (each followed by the Newton step when
        ``newton``), to the tolerance or, with ``trace``, all ``passes``."""
        sweep = _Sweep.build(self, problem, offset, key)
        gradient0, energy0 = sweep.state_at(init)
        if self.trace:
            return _traced_passes(sweep, init, gradient0)
        return _passes_to_tolerance(sweep, init, gradient0, energy0)


@dataclasses.dataclass(frozen=True)
class _Sweep:
    """What the passes of one frame share (built inside the trace of ``__call__``): the
    method, its part of the rig (``model``), the target's projection and the coordinate
    orders. Its methods are the steps of Algorithm 1 and of the Newton step."""

    method: AbstractCoordinateDescent
    problem: InverseProblem
    model: InverseProblem
    offset: Array
    key: Array
    projection: Array
    offset_sq: Array
    indices: Array
    widths: list
    bucket: Array
    correlation_order: Array | None
    fixed: Array | None

    @classmethod
    def build(cls, method, problem, offset, key) -> "_Sweep":
        """The per-frame quantities: projection, ||b - b0||^2, the support width of each
        coordinate's update (``bucket`` into ``widths``) and the fixed coordinate order."""
        model = method.rig_part(problem)
        k, width = problem.n_blendshapes, model.gram.shape[0]
        # the full projection, sliced, so XLA shares it with ``solve``'s final objective
        projection = problem.projection(offset)[:width]
        offset_sq = offset @ offset
        indices = jnp.arange(k)
        # Supports are padded to the largest m (127 on ict-quartic; 26 on average): each
        # update runs at the smallest width in ``widths`` that holds its support (a
        # ``switch``; under vmap with a shared coordinate, e.g. a fixed order, it stays a
        # branch).
        m = model.support.shape[1]
        widths = sorted({min(m, 2**j) for j in range(3, max(m - 1, 1).bit_length() + 1)} | {m})
        bucket = jnp.searchsorted(jnp.asarray(widths), model.support_valid.sum(axis=1))
        correlation_order = None
        if method.order == "frame_correlation":
            score = jnp.abs(projection[:k]) / problem.blendshape_norms
            correlation_order = jnp.argsort(-score).astype(jnp.int32)
        fixed = static_order(problem, method.order) if correlation_order is None else None
        return cls(
            method, problem, model, offset, key, projection, offset_sq, indices, widths,
            bucket, correlation_order, fixed,
        )  # fmt: skip

    # -- one coordinate ---------------------------------------------------------------------
    def derivative(self, weights, i):
        """(m,) d a / d w_i on the support of i: the product of the other weights of each
        combination (1 for column i itself); a(w) is affine in w_i with this slope."""
        model = self.model
        extended = jnp.append(weights, jnp.ones((1,), weights.dtype))
        g = jnp.prod(extended[model.support_others[i]], axis=-1)
        return jnp.where(model.support_valid[i], g, 0.0)

    def line(self, weights, gradient, i):
        """Closed-form update of coordinate i: (new value, slope at w_i = 0, curvature,
        d a / d w_i)."""
        model, alpha, upper = self.model, self.method.alpha, self.method.upper
        g = self.derivative(weights, i)
        curvature = g @ model.support_block[i] @ g
        slope = g @ gradient[model.support[i]] - weights[i] * curvature + alpha
        safe = curvature > 0
        value = jnp.clip(-slope / jnp.where(safe, curvature, 1.0), 0.0, upper)
        return jnp.where(safe, value, 0.0), slope, curvature, g

    def decrease(self, weights, gradient, i):
        """Decrease of the objective by the closed-form update of coordinate i."""
        value, slope, curvature, _ = self.line(weights, gradient, i)
        old = weights[i]
        return (old - value) * slope + 0.5 * (old**2 - value**2) * curvature

    def choose(self, weights, gradient):
        """The coordinate a greedy order updates next."""
        model, alpha, upper = self.model, self.method.alpha, self.method.upper
        if self.method.order == "gauss_southwell":
            slopes = jax.vmap(lambda i: self.derivative(weights, i) @ gradient[model.support[i]])(
                self.indices
            )
            slopes = slopes + alpha
            stuck = ((weights <= 0) & (slopes > 0)) | ((weights >= upper) & (slopes < 0))
            return jnp.argmax(jnp.where(stuck, 0.0, jnp.abs(slopes)))
        return jnp.argmax(jax.vmap(self.decrease, (None, None, 0))(weights, gradient, self.indices))

    def sized_update(self, width):
        """The update of one coordinate whose support fits in ``width``: (new value, updated
        gradient)."""
        model, alpha, upper = self.model, self.method.alpha, self.method.upper

        def run(weights, gradient, i):
            extended = jnp.append(weights, jnp.ones((1,), weights.dtype))
            g = jnp.prod(extended[model.support_others[i, :width]], axis=-1)
            g = jnp.where(model.support_valid[i, :width], g, 0.0)
            curvature = g @ model.support_block[i, :width, :width] @ g
            slope = g @ gradient[model.support[i, :width]] - weights[i] * curvature + alpha
            safe = curvature > 0
            value = jnp.clip(-slope / jnp.where(safe, curvature, 1.0), 0.0, upper)
            value = jnp.where(safe, value, 0.0)
            change = value - weights[i]
            # a weight that stays put (most often one held at 0 by the L1 term) leaves
            # the gradient as it is: skip reading its m x P block of Q
            gradient = jax.lax.cond(
                _one_frame_or_batch(change != 0, jnp.asarray(True)),
                lambda: gradient + change * (g @ model.support_gram[i, :width]),
                lambda: gradient,
            )
            return value, gradient

        return run

    def update(self, branches, state, i):
        """One step of the scan over a pass: update coordinate i (or the greedy choice)."""
        method, model = self.method, self.model
        weights, gradient = state
        if method.order in ("gauss_southwell", "max_improvement"):
            i = self.choose(weights, gradient)
        value, gradient = jax.lax.switch(self.bucket[i], branches, weights, gradient, i)
        weights = weights.at[i].set(value)
        if not method.trace:
            return (weights, gradient), None
        # in vertex space: the coefficient-space form loses ~1e-7 ||b - b0||^2 to
        # cancellation, more than late coordinate updates gain
        residual = model.coefficients(weights) @ model.columns - self.offset
        return (weights, gradient), 0.5 * residual @ residual + method.alpha * weights.sum()

    # -- passes -----------------------------------------------------------------------------
    def state_at(self, weights):
        """(gradient c = Q a - p, objective) at ``weights``, from scratch."""
        model, projection = self.model, self.projection
        a = model.coefficients(weights)
        gradient = model.gram @ a - projection
        energy = (
            0.5 * (a @ gradient - a @ projection + self.offset_sq)
            + self.method.alpha * weights.sum()
        )
        return gradient, energy

    def sequence(self, n, gradient):
        """(K,) coordinates of pass n."""
        order, k, problem = self.method.order, self.problem.n_blendshapes, self.problem
        if order == "random":
            return jax.random.permutation(jax.random.fold_in(self.key, n), k).astype(jnp.int32)
        if order == "iteration_correlation":  # B^T (f(w) - b) = c[:k]
            return jnp.argsort(-jnp.abs(gradient[:k]) / problem.blendshape_norms).astype(jnp.int32)
        return self.fixed if self.correlation_order is None else self.correlation_order

    def one_pass(self, n, weights, gradient):
        """Pass n over all K coordinates, then (``newton``) the Newton step: (weights,
        gradient, objective, per-update objectives or None)."""
        branches = [self.sized_update(width) for width in self.widths]
        (weights, _), per_update = jax.lax.scan(
            lambda state, i: self.update(branches, state, i),
            (weights, gradient),
            self.sequence(n, gradient),
        )
        gradient, energy = self.state_at(weights)
        if self.method.newton:
            weights, gradient, energy = _newton_step(self, weights, gradient, energy)
        return weights, gradient, energy, per_update


def _newton_step(sweep: _Sweep, weights, gradient, energy):
    """Projected Gauss-Newton step on the free weights, kept if it lowers E."""
    model, alpha, upper = sweep.model, sweep.method.alpha, sweep.method.upper
    bucket, n_columns = sweep.bucket, model.gram.shape[0]

    def _no_row(g_i, i):
        return jnp.zeros(n_columns, g_i.dtype)

    qg_rows = [
        (lambda w: lambda g_i, i: g_i[:w] @ model.support_gram[i, :w])(width)
        for width in sweep.widths
    ]
    g = model.slopes(weights)  # (K, m)
    grad = jnp.einsum("km,km->k", g, gradient[model.support]) + alpha
    # row i: (Q G)[:, i] = g_i^T Q[S_i, :], each at its support's padded width
    free = (weights > 0) & (weights < upper)
    # rows of fixed weights are not needed (their part of the system is the identity)
    skip = len(qg_rows)
    qg = jax.lax.map(
        lambda i: jax.lax.switch(
            _one_frame_or_batch(jnp.where(free[i], bucket[i], skip), bucket[i]),
            [*qg_rows, _no_row],
            g[i],
            i,
        ),
        sweep.indices,
    )
    jac = model.jacobian(weights)
    hessian = jac @ qg.T  # G^T Q G
    pair = free[:, None] & free[None, :]
    ridge = 1e-6 * jnp.max(jnp.abs(jnp.diag(hessian)))
    system = jnp.where(pair, hessian, 0.0) + jnp.diag(jnp.where(free, ridge, 1.0))
    step = spd_solve(system, -jnp.where(free, grad, 0.0))
    step = jnp.where(free & jnp.isfinite(step), step, 0.0)
    inside, projected, clipped = _box_candidates(weights, step, free, upper)
    best, best_gradient, best_energy = weights, gradient, energy
    for trial, needed in ((inside, True), (projected, clipped)):
        trial_gradient, trial_energy = jax.lax.cond(
            needed, sweep.state_at, lambda w: (gradient, jnp.full_like(energy, jnp.inf)), trial
        )
        better = trial_energy < best_energy
        best = jnp.where(better, trial, best)
        best_gradient = jnp.where(better, trial_gradient, best_gradient)
        best_energy = jnp.where(better, trial_energy, best_energy)
    return best, best_gradient, best_energy


def _box_candidates(weights, step, free, upper):
    """The two candidates of a Newton step: the longest step <= 1 that keeps every free
    weight inside the box (the ratio test of active-set methods: the first weight to reach a
    bound stops on it), and the full step projected onto the box; and whether the second
    differs (when no free weight reaches a bound, length 1, the projected step is the inside
    one, but for weights below 1e-7 upper: one trial, not two)."""
    room = jnp.where(step < 0, weights / -step, jnp.where(step > 0, (upper - weights) / step, 1.0))
    length = jnp.minimum(1.0, jnp.min(jnp.where(free, room, 1.0)))
    inside = weights + length * step
    inside = jnp.clip(jnp.where(inside <= 1e-7 * upper, 0.0, inside), 0.0, upper)
    projected = jnp.clip(weights + step, 0.0, upper)
    clipped = _one_frame_or_batch(length < 1, jnp.asarray(True))
    return inside, projected, clipped


def _traced_passes(sweep: _Sweep, init, gradient0) -> Iterate:
    """All ``passes`` passes, recording the objective after every coordinate update."""
    passes = sweep.method.passes

    def traced(carry, n):
        weights, gradient = carry
        weights, gradient, _, per_update = sweep.one_pass(n, weights, gradient)
        return (weights, gradient), per_update

    (weights, _), history = jax.lax.scan(traced, (init, gradient0), jnp.arange(passes))
    assert history is not None  # a traced sweep records every update
    return Iterate(weights, history.reshape(-1), jnp.asarray(passes), jnp.asarray(True))


def _passes_to_tolerance(sweep: _Sweep, init, gradient0, energy0) -> Iterate:
    """Passes until one lowers the objective by less than ``tol`` relative (at most
    ``passes``), recording the objective after each."""
    passes, tol = sweep.method.passes, sweep.method.tol

    def keep_going(state):
        n, _, _, previous, energy, _ = state
        change = jnp.abs(previous - energy) / jnp.maximum(jnp.abs(energy), 1e-30)
        return (n < passes) & ((n == 0) | (tol <= 0) | (change > tol))

    def body(state):
        n, weights, gradient, _, energy, history = state
        weights, gradient, new_energy, _ = sweep.one_pass(n, weights, gradient)
        return n + 1, weights, gradient, energy, new_energy, history.at[n].set(new_energy)

    history0 = jnp.zeros(passes, energy0.dtype)
    state = (jnp.asarray(0), init, gradient0, energy0, energy0, history0)
    n, weights, _, previous, energy, history = jax.lax.while_loop(keep_going, body, state)
    history = jnp.where(jnp.arange(passes) < n, history, energy)
    change = jnp.abs(previous - energy) / jnp.maximum(jnp.abs(energy), 1e-30)
    converged = (tol <= 0) | (change <= tol)
    return Iterate(weights, history, n, converged)


class QuarticCD(AbstractCoordinateDescent):
    """Algorithm 1 on the rig with all its correctives (see ``AbstractCoordinateDescent``).

    Defaults run to convergence (``tol=1e-5``, at most 100 passes, Newton steps); the paper's
    protocol is ``QuarticCD(alpha, passes=5, tol=0.0, newton=False)``.
    """

    alpha: float = 0.0
    passes: int = eqx.field(static=True, default=100)
    tol: float = 1e-5
    order: str = eqx.field(static=True, default="decreasing")
    newton: bool = eqx.field(static=True, default=True)
    upper: float = 1.0
    trace: bool = eqx.field(static=True, default=False)

    def rig_part(self, problem: InverseProblem) -> InverseProblem:
        return problem


class LinearCD(AbstractCoordinateDescent):
    """QuarticCD's algorithm on the rig without correctives (the rig's linear part)."""

    alpha: float = 0.0
    passes: int = eqx.field(static=True, default=100)
    tol: float = 1e-5
    order: str = eqx.field(static=True, default="decreasing")
    newton: bool = eqx.field(static=True, default=True)
    upper: float = 1.0
    trace: bool = eqx.field(static=True, default=False)

    def rig_part(self, problem: InverseProblem) -> InverseProblem:
        return linear_part(problem)


def linear_part(problem: InverseProblem) -> InverseProblem:
    """The problem of the rig without correctives (its first K columns)."""
    k = problem.n_blendshapes
    return eqx.tree_at(
        lambda p: (
            p.columns,
            p.gram,
            p.combinations,
            p.support,
            p.support_others,
            p.support_valid,
            p.support_gram,
            p.support_block,
        ),
        problem,
        (
            problem.columns[:k],
            problem.gram[:k, :k],
            (),
            problem.support[:, :1],
            problem.support_others[:, :1],
            problem.support_valid[:, :1],
            problem.support_gram[:, :1, :k],
            problem.support_block[:, :1, :1],
        ),
    )


def static_order(problem: InverseProblem, order: str) -> Int[Array, " K"]:
    """(K,) int32 coordinate sequence of a fixed order (``decreasing`` or ``increasing``
    blendshape norm; the others are decided per frame or per pass during the solve and
    fall back to ``decreasing`` here)."""
    check_order(order)
    score = -problem.blendshape_norms if order == "increasing" else problem.blendshape_norms
    return jnp.argsort(-score).astype(jnp.int32)


class Seol(AbstractInverseMethod):
    """Seol et al. 2011: one pass of residual subtraction on the linear rig, no L1 and no upper
    bound, w_i = max(0, b_i^T r / ||b_i||^2), r <- r - w_i b_i; computed in vertex space,
    independently of the coefficient-space coordinate descent.

    Attributes:
        order: ``decreasing`` or ``increasing`` blendshape norm.
    """

    order: str = eqx.field(static=True, default="decreasing")
    alpha: ClassVar[float] = 0.0
    upper: ClassVar[float] = float("inf")
    penalises_l1: ClassVar[bool] = False

    def __check_init__(self):
        if self.order not in ("decreasing", "increasing"):
            raise ValueError(f"order: Seol takes 'decreasing' or 'increasing', got {self.order!r}")

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        shapes = problem.columns[: problem.n_blendshapes]

        def step(carry, i):
            weights, residual = carry
            column = shapes[i]
            value = jnp.maximum(column @ residual / (column @ column), 0.0)
            return (weights.at[i].set(value), residual - value * column), None

        start = (jnp.zeros_like(init), offset)
        (weights, residual), _ = jax.lax.scan(step, start, static_order(problem, self.order))
        history = (0.5 * residual @ residual)[None]
        return Iterate(weights, history, jnp.asarray(1), jnp.asarray(True))
