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


StreamCarry = tuple[Float[Array, " K"], Bool[Array, ""]]
"""What ``Constrained`` hands from one frame of a ``Stream`` to the next: (the frame's solved
weights, before multipliers and offsets; whether there is a previous frame)."""


def pair_indices(
    names: tuple[str, ...] | list[str],
    pairs: Any,
    *,
    argument: str = "pairs",
) -> tuple[tuple[int, int], ...]:
    """Index pairs of ``pairs`` given by name (``(("eyeBlink_L", "eyeBlink_R"), ...)``) in the
    rig's ``names``, for ``Constrained(exclusive=, ties=)``. Raises a ValueError naming
    ``argument`` and every name the rig lacks, before anything is compiled."""
    names = _check_names(names)
    index = {n: i for i, n in enumerate(names)}
    if isinstance(pairs, str):
        raise ValueError(f"{argument}: expected pairs of names, got the string {pairs!r}")
    pairs = [tuple(p) if not isinstance(p, str) else (p,) for p in pairs]
    malformed = [p for p in pairs if len(p) != 2 or not all(isinstance(n, str) for n in p)]
    if malformed:
        raise ValueError(f"{argument}: expected pairs of two names, got {malformed}")
    unknown = sorted({n for p in pairs for n in p if n not in index})
    if unknown:
        raise ValueError(f"{argument}: names not in the rig: {unknown}")
    return _index_pairs([(index[a], index[b]) for a, b in pairs], argument)


def _mask(active: Any) -> Bool[Array, " K"] | None:
    """``active`` as a (K,) bool array (an array: traced, so another mask reuses the compiled
    solve); None stays None."""
    if active is None or isinstance(active, jax.core.Tracer):
        return active
    values = np.asarray(active)
    if values.ndim != 1 or values.size == 0:
        raise ValueError(f"active: expected a (K,) mask of shapes, got shape {values.shape}")
    if values.dtype != bool and not np.isin(values, (0, 1)).all():
        raise ValueError("active: expected booleans or 0/1 per shape")
    return jnp.asarray(values.astype(bool))


def _per_shape(value: Any, argument: str) -> Float[Array, "*K"] | None:
    """A number or a (K,) array of finite floats, as an array; None stays None."""
    if value is None or isinstance(value, jax.core.Tracer):
        return value
    values = np.asarray(value, np.float32)
    if values.ndim > 1 or values.size == 0:
        raise ValueError(f"{argument}: expected a number or (K,) per-shape values, got shape "
                         f"{values.shape}")  # fmt: skip
    if not np.isfinite(values).all():
        raise ValueError(f"{argument}: expected finite values")
    return jnp.asarray(values)


SUPPORTED_METHODS = (QuarticNewton,)
"""Methods ``Constrained`` can wrap: those that take per-weight upper bounds (a bound of 0
holds a weight at exactly 0) and minimise the L1-penalised objective of the problem's Gram
matrix."""


class Constrained(AbstractInverseMethod):
    """A method whose solutions never have both members of an exclusive pair non-zero, with
    the production solver's terms: left/right ties (symmetry), an L2 and a temporal term, an
    active-shape mask and per-shape multipliers and offsets on the output (see the module
    docstring for the algorithm).

        pairs = canrig_jax.rig.exclusive_pairs(rig.names)
        method = inverse.Constrained(inverse.QuarticNewton(alpha=1.0), exclusive=pairs)
        inverse.solve(problem, target, method)

    Attributes:
        method: the wrapped method (one of ``SUPPORTED_METHODS``); its ``alpha`` and ``upper``
            are this method's.
        exclusive: (i, j) index pairs that are never both non-zero in the output (exactly 0,
            not only below ``CARDINALITY_TOL``), e.g. ``rig.exclusive_pairs(rig.names)``.
        ties: (left, right) index pairs for the tie penalty, e.g.
            ``left_right_pairs(rig.names)`` or ``pair_indices(rig.names, name_pairs)``; must
            not contain an exclusive pair.
        tie_weight: weight of the penalty tie_weight / 2 * sum (w_left - w_right)^2, in the
            squared rig units of the data term (cm^2 for ICT); 0 (default) turns ties off.
        l2_weight: weight of l2_weight / 2 * ||w||^2 (same units); 0 (default) turns it off.
        temporal_weight: weight of temporal_weight / 2 * ||w - w_prev||^2 against the previous
            frame's solved weights (before multipliers and offsets), same units. Only a
            warm-started ``Stream`` has a previous frame (it carries it, and starts the frame
            from it); a single ``solve``, a batch and a stream's first frame have none, and
            the term is off there.
        active: optional (K,) mask; an inactive shape is held at exactly 0 (its bound set to
            0, also after offsets). An array, traced: another mask reuses the compiled solve.
        multipliers, offsets: optional per-shape gain and bias applied to the solved weights,
            w_out = clip(multipliers * w + offsets, 0, upper) (a number applies to every
            shape, a (K,) array shape by shape); an exclusive pair is still never both
            non-zero in w_out (the smaller goes to 0).

    ``Solution.objective`` is 1/2 ||f(w) - b||^2 + alpha 1^T w of the returned weights,
    without the penalties; ``Solution.history`` is the objective the wrapped method minimised,
    penalties included. Cost: one solve per frame without conflicts, two more per resolved
    pair.
    """

    method: AbstractInverseMethod
    exclusive: tuple[tuple[int, int], ...] = eqx.field(
        static=True, default=(), converter=lambda pairs: _index_pairs(pairs, "exclusive")
    )
    ties: tuple[tuple[int, int], ...] = eqx.field(
        static=True, default=(), converter=lambda pairs: _index_pairs(pairs, "ties")
    )
    tie_weight: float = 0.0
    l2_weight: float = 0.0
    temporal_weight: float = 0.0
    active: Bool[Array, " K"] | None = eqx.field(default=None, converter=_mask)
    multipliers: Float[Array, "*K"] | None = eqx.field(
        default=None, converter=lambda x: _per_shape(x, "multipliers")
    )
    offsets: Float[Array, "*K"] | None = eqx.field(
        default=None, converter=lambda x: _per_shape(x, "offsets")
    )
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
        for name in ("tie_weight", "l2_weight", "temporal_weight"):
            value = getattr(self, name)
            if is_concrete(value) and not (np.ndim(value) == 0 and 0 <= value < np.inf):
                raise ValueError(f"{name}: expected a non-negative, finite weight, got {value}")

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
        """The problem the wrapped method solves without a previous frame: ``problem`` with
        the tie penalty and the L2 term in its Gram matrix (and in the per-coordinate blocks
        derived from it). Its ``objective`` is the data term + L1 + tie penalty + L2 term."""
        return self.penalised(problem)

    def penalised(
        self,
        problem: InverseProblem,
        previous: Float[Array, " K"] | None = None,
        temporal_weight: float | Float[Array, ""] = 0.0,
    ) -> InverseProblem:
        """``problem`` with every quadratic term on the weights: the tie penalty,
        l2_weight / 2 ||w||^2 and temporal_weight / 2 ||w - previous||^2. Each is ||T w - c||^2
        / 2 for some matrix T: the rig with extra mesh coordinates whose target is c, so T^T T
        enters the Gram matrix (blendshape block), T^T c the projection and ||c||^2 / 2 the
        objective's constant (``InverseProblem.linear_term`` and ``constant_term``). Without
        ``previous`` there is no temporal term (and no linear term or constant is added)."""
        k = problem.n_blendshapes
        self._check_range(k)
        dtype = problem.gram.dtype
        diagonal = jnp.asarray(self.l2_weight, dtype)
        if previous is not None:
            diagonal = diagonal + jnp.asarray(temporal_weight, dtype)
        extra = diagonal * jnp.eye(k, dtype=dtype)
        if self.ties:
            difference = np.zeros((len(self.ties), k))
            rows = np.arange(len(self.ties))
            difference[rows, [i for i, _ in self.ties]] = 1.0
            difference[rows, [j for _, j in self.ties]] = -1.0
            extra = extra + self.tie_weight * jnp.asarray(difference.T @ difference, dtype)
        linear, constant = problem.linear_term, problem.constant_term
        if previous is not None:
            previous = jnp.asarray(previous, dtype)
            pull = jnp.asarray(temporal_weight, dtype) * previous
            term = jnp.zeros(problem.gram.shape[0], dtype).at[:k].set(pull)
            linear = term if linear is None else linear + term
            constant = 0.5 * pull @ previous + (0.0 if constant is None else constant)
        # only the blendshape columns (the first K) carry the penalty; support slot 0 of
        # coordinate i is column i itself (``_coordinate_supports``), the others are correctives
        return eqx.tree_at(
            lambda p: (p.gram, p.support_gram, p.support_block, p.linear_term, p.constant_term),
            problem,
            (
                problem.gram.at[:k, :k].add(extra),
                problem.support_gram.at[:, 0, :k].add(extra),
                problem.support_block.at[:, 0, 0].add(jnp.diag(extra)),
                linear,
                constant,
            ),
            is_leaf=lambda x: x is None,
        )

    def check(self, problem: InverseProblem) -> None:
        k = problem.n_blendshapes
        self._check_range(k)
        for name in ("active", "multipliers", "offsets"):
            value = getattr(self, name)
            scalar_ok = name != "active"
            if value is not None and not (
                np.shape(value) == (k,) or (scalar_ok and np.ndim(value) == 0)
            ):
                want = f"({k},) per-shape values" + (" or one number" if scalar_ok else "")
                raise ValueError(
                    f"{name}: expected {want} for the rig's {k} blendshapes, "
                    f"got shape {np.shape(value)}"
                )

    def _check_range(self, k: int) -> None:
        for argument, pairs in (("exclusive", self.exclusive), ("ties", self.ties)):
            outside = [p for p in pairs if max(p) >= k]
            if outside:
                raise ValueError(f"{argument}: pairs {outside} index past the rig's {k} weights")

    def bounds(self, problem: InverseProblem) -> Float[Array, " K"]:
        """(K,) the per-weight upper bounds of the solve: ``upper``, 0 for inactive shapes."""
        k = problem.n_blendshapes
        bounds = jnp.broadcast_to(jnp.asarray(self.method.upper, problem.gram.dtype), (k,))
        return bounds if self.active is None else jnp.where(self.active, bounds, 0.0)

    def adjusted(
        self, weights: Float[Array, " K"], bounds: Float[Array, " K"]
    ) -> Float[Array, " K"]:
        """The output weights of solved ``weights``: clip(multipliers * w + offsets, 0,
        ``bounds``), then the smaller member of an exclusive pair both non-zero set to 0;
        ``weights`` themselves without multipliers and offsets."""
        if self.multipliers is None and self.offsets is None:
            return weights
        if self.multipliers is not None:
            weights = weights * self.multipliers
        if self.offsets is not None:
            weights = weights + self.offsets
        return self._hard_rule(jnp.clip(weights, 0.0, bounds))

    def _hard_rule(self, weights: Float[Array, " K"]) -> Float[Array, " K"]:
        for i, j in self.exclusive:
            on = (weights[i] > 0) & (weights[j] > 0)
            smaller = jnp.where(weights[i] <= weights[j], i, j)
            weights = jnp.where(on, weights.at[smaller].set(0.0), weights)
        return weights

    def _bounded(self, upper: Float[Array, " K"]) -> AbstractInverseMethod:
        return eqx.tree_at(lambda m: m.upper, self.method, upper)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        return self._frame(problem, offset, init, key, None)[0]

    def initial_carry(self, problem: InverseProblem) -> StreamCarry:
        """(previous frame's solved weights, whether there is one): none yet."""
        return jnp.zeros(problem.n_blendshapes, problem.gram.dtype), jnp.asarray(False)

    def step(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
        carry: StreamCarry,
    ) -> tuple[Iterate, StreamCarry]:
        """One frame: with a previous frame in ``carry``, the solve starts from its solved
        weights (``init``, the previous output, has multipliers and offsets applied) and the
        temporal term pulls towards them; returns this frame's solved weights as the carry."""
        return self._frame(problem, offset, init, key, carry)

    def _frame(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
        carry: StreamCarry | None,
    ) -> tuple[Iterate, StreamCarry]:
        """One frame, without a previous frame when ``carry`` is None (the problem then has
        no temporal term at all, so ``solve`` keeps the rounding of the plain method)."""
        bounds = self.bounds(problem)
        if carry is None:
            start, model = jnp.clip(init, 0.0, bounds), self.tied(problem)
        else:
            previous, has_previous = carry
            start = jnp.clip(jnp.where(has_previous, previous, init), 0.0, bounds)
            temporal = jnp.where(has_previous, self.temporal_weight, 0.0)
            model = self.penalised(problem, previous, temporal)
        run = self._resolve(model, offset, start, bounds, key)
        output = run._replace(weights=self.adjusted(run.weights, bounds))
        # a failed frame hands on its start, never NaN (as ``Stream`` does with the output)
        solved = jnp.where(jnp.all(jnp.isfinite(run.weights)), run.weights, start)
        return output, (solved, jnp.asarray(True))

    def _resolve(
        self,
        model: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        bounds: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        """The wrapped method on ``model`` within ``bounds``, exclusive pairs resolved."""
        if not self.exclusive:
            return self._bounded(bounds)(model, offset, init, key)
        dtype = model.gram.dtype
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
        weights = self._hard_rule(weights)
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
