"""Mutually exclusive blendshapes and left/right ties for the inverse rig.

Some pairs of controls describe opposite directions of one motion (the jaw cannot move left
and right at once), yet a solver fitting a noisy target may turn both on a little, each
cancelling part of the other (``rig.exclusive_pairs`` finds them in a rig's names; the list
``rig.MUTUALLY_EXCLUSIVE`` says why each pair is there). ``Constrained`` wraps a method so that
no such pair is ever both non-zero in its output, losing as little accuracy as it can:

1. solve with the wrapped method;
2. while some exclusive pair is both non-zero (and at most once per pair): take the first such
   pair, solve twice more, warm-started from the current weights, once with each member held
   at exactly 0 (its per-weight upper bound set to 0), and keep the solution whose objective
   is lower; a held member stays held for the rest of the frame;
3. a final hard rule (a safeguard: step 2 already resolves every pair) sets the smaller member
   of any pair still both non-zero to 0.

A pair is resolved once and for all in step 2 (one member is held at 0 from then on), so the
loop ends after at most as many rounds as there are pairs, and frames with no conflict cost one
solve. With a single conflicting pair the result is the better of the two held solves, which
is what trying both by brute force gives. Under ``vmap`` (``solve_sequence``) the rounds run
until every frame of the batch is resolved; frames already resolved keep their weights.

Ties: an optional quadratic penalty ``tie_weight / 2 * sum (w_left - w_right)^2`` over pairs
of left and right controls (``left_right_pairs``) pulls the two sides of a face together. It
is added to the problem the wrapped method sees: the penalty is ||T w||^2 / 2 for a matrix T
with rows sqrt(tie_weight) (e_left - e_right), i.e. the rig with extra mesh coordinates whose
target is 0, so it enters the Gram matrix (Q + T^T T on the blendshape block) and nothing else
(the projection of the target is unchanged). The wrapped method's gradient and Gauss-Newton
Hessian include it exactly.

What ``Solution`` reports for a ``Constrained`` method: ``objective`` is, as for every method,
1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig, *without* the tie penalty (so it can be
compared with unconstrained solves); ``history`` is the objective the wrapped method
minimised, tie penalty included: the first solve's history, then the value after each
resolved pair.
"""

from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .._checks import is_concrete
from ..rig import MUTUALLY_EXCLUSIVE, exclusive_pairs
from ._base import AbstractInverseMethod, Iterate
from ._metrics import CARDINALITY_TOL
from ._problem import InverseProblem
from ._projected_newton import QuarticNewton

_SIDES = (("Left", "Right"), ("_L", "_R"), ("_l", "_r"), ("L", "R"))
"""Suffixes of the left and right members of a left/right pair of control names."""


def _check_names(names: Any) -> tuple[str, ...]:
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"names: expected a sequence of blendshape names, got {names!r}")
    names = tuple(names)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"names: each name must appear once, repeated: {repeated}")
    return names


def left_right_pairs(
    names: tuple[str, ...] | list[str],
    *,
    exclude: tuple[tuple[str, str], ...] = MUTUALLY_EXCLUSIVE,
) -> tuple[tuple[int, int], ...]:
    """Index pairs (left, right) of controls whose names differ only in the side suffix
    (``eyeBlinkLeft``/``eyeBlinkRight``, ICT ``eyeBlink_L``/``eyeBlink_R``), for
    ``Constrained(ties=)``; pairs that ``exclude`` names (by default the exclusive pairs:
    ``jawLeft``/``jawRight`` differ in suffix but are opposites) are left out.

    Raises a ValueError naming ``names`` or ``exclude`` for bad input.
    """
    names = _check_names(names)
    excluded = set(exclusive_pairs(names, exclude)) if exclude else set()
    excluded |= {(j, i) for i, j in excluded}
    index = {n: i for i, n in enumerate(names)}
    out = []
    for i, name in enumerate(names):
        for left, right in _SIDES:
            stem = name[: -len(left)] if name.endswith(left) else None
            j = index.get(stem + right) if stem else None
            if j is not None and (i, j) not in excluded:
                out.append((i, j))
                break
    return tuple(out)


def both_active(
    weights: Float[ArrayLike, "*frames K"],
    pairs: tuple[tuple[int, int], ...],
    *,
    tol: float = CARDINALITY_TOL,
) -> Bool[np.ndarray, "*frames E"]:
    """(..., E) whether both members of each pair are active (weight > ``tol``; the
    cardinality's threshold by default, 0 for "both non-zero") in each frame of ``weights``."""
    weights = np.asarray(weights)
    pairs = _index_pairs(pairs, "pairs")
    if weights.ndim < 1 or any(max(p) >= weights.shape[-1] for p in pairs):
        raise ValueError(f"pairs: index past the {np.shape(weights)[-1:]} weights")
    if not pairs:
        return np.zeros((*weights.shape[:-1], 0), bool)
    left, right = (list(side) for side in zip(*pairs, strict=True))
    return (weights[..., left] > tol) & (weights[..., right] > tol)


def _index_pairs(pairs: Any, argument: str) -> tuple[tuple[int, int], ...]:
    """``pairs`` as a tuple of (int, int), each of two different non-negative indices."""
    if isinstance(pairs, str):
        raise ValueError(f"{argument}: expected index pairs (i, j), got the string {pairs!r}")
    out = []
    for pair in pairs:
        try:
            values: tuple[Any, ...] = () if isinstance(pair, str) else tuple(pair)
        except TypeError:  # not iterable
            values = ()
        ok = len(values) == 2 and all(
            isinstance(v, int | np.integer) and not isinstance(v, bool) and v >= 0 for v in values
        )
        if not ok:
            raise ValueError(
                f"{argument}: expected pairs of two non-negative indices (i, j), got {pair!r}"
            )
        i, j = int(values[0]), int(values[1])
        if i == j:
            raise ValueError(f"{argument}: the pair {pair!r} pairs weight {i} with itself")
        out.append((i, j))
    return tuple(out)


SUPPORTED_METHODS = (QuarticNewton,)
"""Methods ``Constrained`` can wrap: those that take per-weight upper bounds (a bound of 0
holds a weight at exactly 0) and minimise the L1-penalised objective of the problem's Gram
matrix."""


class Constrained(AbstractInverseMethod):
    """A method whose solutions never have both members of an exclusive pair non-zero, with
    optional left/right ties (see the module docstring for the algorithm).

        pairs = canrig_jax.rig.exclusive_pairs(rig.names)
        method = inverse.Constrained(inverse.QuarticNewton(alpha=1.0), exclusive=pairs)
        inverse.solve(problem, target, method)

    Attributes:
        method: the wrapped method (one of ``SUPPORTED_METHODS``); its ``alpha`` and ``upper``
            are this method's.
        exclusive: (i, j) index pairs that are never both non-zero in the output (exactly 0,
            not only below ``CARDINALITY_TOL``), e.g. ``rig.exclusive_pairs(rig.names)``.
        ties: (left, right) index pairs for the tie penalty, e.g.
            ``left_right_pairs(rig.names)``; must not contain an exclusive pair.
        tie_weight: weight of the penalty tie_weight / 2 * sum (w_left - w_right)^2, in the
            squared rig units of the data term (cm^2 for ICT); 0 (default) turns ties off.

    ``Solution.objective`` is 1/2 ||f(w) - b||^2 + alpha 1^T w without the tie penalty;
    ``Solution.history`` includes it. Cost: one solve per frame without conflicts, two more
    per resolved pair.
    """

    method: AbstractInverseMethod
    exclusive: tuple[tuple[int, int], ...] = eqx.field(
        static=True, default=(), converter=lambda pairs: _index_pairs(pairs, "exclusive")
    )
    ties: tuple[tuple[int, int], ...] = eqx.field(
        static=True, default=(), converter=lambda pairs: _index_pairs(pairs, "ties")
    )
    tie_weight: float = 0.0
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        if not isinstance(self.method, SUPPORTED_METHODS):
            names = ", ".join(cls.__name__ for cls in SUPPORTED_METHODS)
            raise TypeError(
                f"method: expected a method that takes per-weight upper bounds ({names}), "
                f"got {type(self.method).__name__}"
            )
        opposed = {frozenset(p) for p in self.exclusive} & {frozenset(p) for p in self.ties}
        if opposed:
            raise ValueError(
                f"ties: {sorted(tuple(sorted(p)) for p in opposed)} are also exclusive pairs "
                "(a tie pulls both on, exclusivity keeps one off)"
            )
        if is_concrete(self.tie_weight) and not (
            np.ndim(self.tie_weight) == 0 and 0 <= self.tie_weight < np.inf
        ):
            raise ValueError(
                f"tie_weight: expected a non-negative, finite weight, got {self.tie_weight}"
            )

    @property
    def alpha(self) -> float | Float[ArrayLike, ""]:
        return self.method.alpha

    @property
    def upper(self) -> float | Float[ArrayLike, ""] | Float[ArrayLike, " K"]:
        return self.method.upper

    def tie_penalty(self, weights: Float[ArrayLike, "*frames K"]) -> Float[Array, "*frames"]:
        """tie_weight / 2 * sum over ``ties`` of (w_left - w_right)^2, per frame."""
        weights = jnp.asarray(weights)
        if not self.ties:
            return jnp.zeros(weights.shape[:-1], weights.dtype)
        left, right = (jnp.asarray(side) for side in zip(*self.ties, strict=True))
        difference = weights[..., left] - weights[..., right]
        return 0.5 * self.tie_weight * jnp.sum(difference**2, axis=-1)

    def tied(self, problem: InverseProblem) -> InverseProblem:
        """The problem the wrapped method solves: ``problem`` with the tie penalty in its Gram
        matrix (and in the per-coordinate blocks derived from it); ``problem`` itself without
        ties. Its ``objective`` is the data term + L1 + tie penalty."""
        if not self.ties:
            return problem
        k = problem.n_blendshapes
        self._check_range(k)
        difference = np.zeros((len(self.ties), k))
        rows = np.arange(len(self.ties))
        difference[rows, [i for i, _ in self.ties]] = 1.0
        difference[rows, [j for _, j in self.ties]] = -1.0
        extra = self.tie_weight * jnp.asarray(difference.T @ difference, problem.gram.dtype)
        # only the blendshape columns (the first K) carry the penalty; support slot 0 of
        # coordinate i is column i itself (``_coordinate_supports``), the others are correctives
        return eqx.tree_at(
            lambda p: (p.gram, p.support_gram, p.support_block),
            problem,
            (
                problem.gram.at[:k, :k].add(extra),
                problem.support_gram.at[:, 0, :k].add(extra),
                problem.support_block.at[:, 0, 0].add(jnp.diag(extra)),
            ),
        )

    def _check_range(self, k: int) -> None:
        for argument, pairs in (("exclusive", self.exclusive), ("ties", self.ties)):
            outside = [p for p in pairs if max(p) >= k]
            if outside:
                raise ValueError(f"{argument}: pairs {outside} index past the rig's {k} weights")

    def _bounded(self, upper: Float[Array, " K"]) -> AbstractInverseMethod:
        return eqx.tree_at(lambda m: m.upper, self.method, upper)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        k = problem.n_blendshapes
        self._check_range(k)
        model = self.tied(problem)
        dtype = problem.gram.dtype
        bounds = jnp.broadcast_to(jnp.asarray(self.method.upper, dtype), (k,))
        if not self.exclusive:
            return self._bounded(bounds)(model, offset, init, key)
        left = jnp.asarray([i for i, _ in self.exclusive])
        right = jnp.asarray([j for _, j in self.exclusive])
        projection, offset_sq = model.projection(offset), offset @ offset
        alpha = self.method.alpha
        rounds = len(self.exclusive)

        def both_on(weights):
            return (weights[left] > 0) & (weights[right] > 0)

        def value(weights):
            return model.objective(weights, projection, offset_sq, alpha)

        # One loop, one call of the wrapped method per iteration (so it is compiled once):
        # phase 0 solves from ``init``; for the first pair both on, phase 1 solves with its
        # left member held at 0 and phase 2 with its right member held, and keeps the
        # better of the two; phase 3 is done.
        def iteration(state):
            phase, weights, bounds, saved, first_history, history, resolved, steps, converged = (
                state
            )
            pair = jnp.argmax(both_on(weights))
            member = jnp.where(phase == 1, left[pair], right[pair])
            held = jnp.where(phase == 0, bounds, bounds.at[member].set(0.0))
            start = jnp.where(phase == 0, init, weights.at[member].set(0.0))
            run = self._bounded(held)(model, offset, start, key)
            ok = jnp.all(jnp.isfinite(run.weights))
            candidate = jnp.where(ok, run.weights, start)  # a failed solve: its start
            change = _objective_change(model, weights, candidate, projection, alpha)
            change = jnp.where(jnp.isfinite(change), change, jnp.inf)
            this = (candidate, held, change, run.steps, run.converged & ok)
            # phase 2: the better of the held-left (saved) and held-right (this) solutions
            better = jax.tree.map(lambda a, b: jnp.where(change < saved[2], a, b), this, saved)
            accepted = jax.tree.map(lambda a, b: jnp.where(phase == 0, a, b), this, better)
            take = phase != 1
            weights = jnp.where(take, accepted[0], weights)
            bounds = jnp.where(take, accepted[1], bounds)
            steps = jnp.where(take, steps + accepted[3], steps)
            converged = jnp.where(take, converged & accepted[4], converged)
            saved = jax.tree.map(lambda a, b: jnp.where(phase == 1, a, b), this, saved)
            first_history = jnp.where(phase == 0, run.history, first_history)
            history = jnp.where(phase == 2, history.at[resolved].set(value(weights)), history)
            resolved = resolved + (phase == 2)
            more = jnp.any(both_on(weights)) & (resolved < rounds)
            phase = jnp.where(phase == 1, 2, jnp.where(more, 1, 3))
            return phase, weights, bounds, saved, first_history, history, resolved, steps, converged

        # the wrapped method's history has a static length: trace it once for its shape
        history_shape = jax.eval_shape(
            lambda: self._bounded(bounds)(model, offset, init, key).history
        )
        zero = jnp.asarray(0.0, dtype)
        saved = (init, bounds, jnp.asarray(jnp.inf, dtype), jnp.asarray(0), jnp.asarray(True))
        state = (
            jnp.asarray(0),
            init,
            bounds,
            saved,
            jnp.zeros(history_shape.shape, history_shape.dtype),
            jnp.zeros(rounds, dtype),
            jnp.asarray(0),
            jnp.asarray(0),
            jnp.asarray(True),
        )
        state = jax.lax.while_loop(lambda s: s[0] != 3, iteration, state)
        _, weights, _, _, first_history, history, resolved, steps, converged = state
        # the hard rule (a safeguard): the smaller member of a pair still both on goes to 0
        still = jnp.any(both_on(weights))
        for i, j in self.exclusive:
            on = (weights[i] > 0) & (weights[j] > 0)
            smaller = jnp.where(weights[i] <= weights[j], i, j)
            weights = jnp.where(on, weights.at[smaller].set(zero), weights)
        history = jnp.where(jnp.arange(rounds) < resolved, history, value(weights))
        return Iterate(
            weights=weights,
            history=jnp.concatenate([first_history, history]),
            steps=steps,
            converged=converged & ~still,
        )


def _objective_change(
    model: InverseProblem,
    weights: Float[Array, " K"],
    trial: Float[Array, " K"],
    projection: Float[Array, " P"],
    alpha: float | Float[Array, ""],
) -> Float[Array, ""]:
    """E(trial) - E(weights) in coefficient space (no float32 cancellation against
    ||b - b0||^2): (a' - a)^T (Q a - p) + 1/2 (a' - a)^T Q (a' - a) + alpha 1^T (w' - w)."""
    a = model.coefficients(weights)
    change = model.coefficients(trial) - a
    return (
        change @ (model.gram @ a - projection)
        + 0.5 * change @ model.gram @ change
        + alpha * (trial - weights).sum()
    )
