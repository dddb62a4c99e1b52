"""One entry point for every inverse-rig method: ``solve(problem, target, method) -> Solution``.

``solve`` validates its inputs in plain Python and then calls one jit-compiled function
that takes the prepared problem, the target and the method as arguments, so it compiles once
per (problem shape, method type and static settings) and is reused by every later call and
by ``solve_sequence``. A ``Stream`` frame is one call of the same body compiled with the
stream's state (``_compiled_call``): its key, frame counter and window live on the device.
Inside a caller's ``jit``/``vmap`` ``solve`` is traced inline.
"""

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Float, PRNGKeyArray

from .._checks import check_finite, is_concrete
from ..rig import BlendshapeRig
from ._base import AbstractInverseMethod, Iterate
from ._coordinate_descent import objective
from ._problem import InverseProblem, prepare
from ._solution import Solution
from ._temporal import AbstractTemporalMethod, time_terms_per_frame, window_owner


def _check_method(method) -> None:
    if not isinstance(method, AbstractInverseMethod):
        got = f"the string {method!r}" if isinstance(method, str) else type(method).__name__
        raise TypeError(
            "method: expected an inverse-rig method object (an inverse.AbstractInverseMethod, "
            f"e.g. inverse.QuarticCD(alpha=0.5)), got {got}"
        )


def _check_problem(problem) -> InverseProblem:
    if isinstance(problem, BlendshapeRig):
        return prepare(problem)
    if not isinstance(problem, InverseProblem):
        raise TypeError(
            f"problem: expected inverse.prepare(rig) (an InverseProblem) or a BlendshapeRig, "
            f"got {type(problem).__name__}"
        )
    return problem


def _check_bounds(problem: InverseProblem, method) -> None:
    """Per-weight bounds (``upper`` of shape (K,)) must match the rig's weights."""
    k = problem.n_blendshapes
    if np.ndim(method.upper) == 1 and np.shape(method.upper) != (k,):
        raise ValueError(
            f"upper: expected ({k},) per-weight bounds to match the rig's {k} blendshapes, "
            f"got shape {np.shape(method.upper)}"
        )
    method.check(problem)


def _check_target(problem: InverseProblem, name: str, target, batched: bool) -> None:
    shape = np.shape(target)
    expected = (problem.n_vertices, 3)
    if (shape[1:] if batched else shape) != expected or (batched and len(shape) != 3):
        want = "(T, " + ", ".join(map(str, expected)) + ")" if batched else str(expected)
        raise ValueError(f"{name}: expected shape {want} to match the rig, got {shape}")
    if not is_concrete(target):
        return
    values = np.asarray(target)
    if not np.issubdtype(values.dtype, np.floating) and not np.issubdtype(values.dtype, np.integer):
        raise TypeError(f"{name}: expected real numbers, got dtype {values.dtype}")
    if batched:
        bad = np.flatnonzero(~np.isfinite(values).all(axis=(1, 2)))
        if bad.size:
            raise ValueError(
                f"{name}: frames {bad[:10].tolist()} contain non-finite values (NaN or inf)"
            )
    else:
        check_finite(name, values)


def _offset_and_init(problem, target, method, init):
    dtype = problem.columns.dtype
    offset = (jnp.asarray(target, dtype) - problem.neutral).reshape(-1)
    return offset, jnp.clip(jnp.asarray(init, dtype), 0.0, method.upper)


def _solve_one(problem, target, method, init, key) -> Solution:
    """The traced body: one frame, inputs already validated."""
    offset, init = _offset_and_init(problem, target, method, init)
    return _solution(problem, offset, method, init, method(problem, offset, init, key))


def _stream_one(problem, target, method, init, key, carry) -> tuple[Solution, Any]:
    """One frame of a ``Stream``: the solution and the method's carry for the next frame."""
    offset, init = _offset_and_init(problem, target, method, init)
    run, carry = method.step(problem, offset, init, key, carry)
    return _solution(problem, offset, method, init, run), carry


def _solution(problem, offset, method, init, run, projection=None, offset_sq=None) -> Solution:
    """The Solution of a method's Iterate: objective under the full rig, finite or the start.
    ``projection`` and ``offset_sq``: the frame's M^T (b - b0) and ||b - b0||^2 when the
    caller has them (else computed from ``offset``, which is otherwise not read)."""
    l1 = method.alpha if method.penalises_l1 else 0.0
    if projection is None:
        projection = problem.projection(offset)
    elif problem.linear_term is not None:
        projection = projection + problem.linear_term
    if offset_sq is None:
        offset_sq = offset @ offset
    value = problem.objective(run.weights, projection, offset_sq, l1)
    finite = jnp.all(jnp.isfinite(run.weights)) & jnp.isfinite(value)
    weights = jnp.where(finite, run.weights, init)
    value = jnp.where(finite, value, problem.objective(init, projection, offset_sq, l1))
    stopped = run.result
    if stopped is None:
        stopped = optx.RESULTS.where(
            run.converged, optx.RESULTS.successful, optx.RESULTS.max_steps_reached
        )
    result = optx.RESULTS.where(finite, stopped, optx.RESULTS.nonlinear_divergence)
    stats = {"steps": jnp.asarray(run.steps, jnp.int32), "converged": run.converged & finite}
    return Solution(weights=weights, objective=value, history=run.history, result=result,
                    stats=stats)  # fmt: skip


_solve_jit = eqx.filter_jit(_solve_one)


def _traced_floats(method: AbstractInverseMethod) -> AbstractInverseMethod:
    """The method with its Python-float fields (alpha, tol, upper) as arrays, so that
    ``filter_jit`` traces them: a sweep over alpha reuses one compiled function."""
    return jax.tree.map(lambda x: jnp.asarray(x) if isinstance(x, float | int) else x, method)


def _key(key) -> jax.Array:
    if key is None:
        return jax.random.key(0)
    if not (isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key)):
        raise TypeError(f"key: expected a typed PRNG key (jax.random.key), got {key!r}")
    return key


def _check_init(problem: InverseProblem, init, name: str = "init"):
    k = problem.n_blendshapes
    if init is None:
        return jnp.zeros(k, problem.columns.dtype)
    if np.shape(init) != (k,):
        raise ValueError(f"{name}: expected shape ({k},), got {np.shape(init)}")
    check_finite(name, init)
    return init


def solve(
    problem: InverseProblem | BlendshapeRig,
    target: Float[ArrayLike, "V 3"],
    method: AbstractInverseMethod,
    *,
    init: Float[ArrayLike, " K"] | None = None,
    key: PRNGKeyArray | None = None,
) -> Solution:
    """Recover rig weights from a target mesh (units of the rig) with ``method``.

    Args:
        problem: ``prepare(rig)`` (prepare once and reuse; a rig is prepared on each call).
        target: (V, 3) mesh to match, finite.
        method: a method object (``METHODS`` lists every class: ``QuarticCD``, ``LinearCD``,
            ``Seol``, ``Joshi``, ``Cetinaslan``, ``LMMM``, ``JaxoptLBFGSB``).
        init: (K,) initial weights for iterative methods (default zeros, as the paper),
            clipped to the method's box.
        key: PRNG key for ``order="random"`` (default ``jax.random.key(0)``).

    Compiled once per problem shape and method type (the problem, target and method are
    arguments of one jitted function). Batch with ``solve_sequence`` or
    ``jax.vmap(lambda b: solve(problem, b, method))``. The returned objective is
    1/2 ||f(w) - b||^2 (+ alpha 1^T w for methods with ``penalises_l1``) under the full rig,
    whatever rig the method assumed. Raises TypeError/ValueError naming the argument for bad
    input, before any compilation.
    """
    _check_method(method)
    problem = _check_problem(problem)
    _check_bounds(problem, method)
    _check_target(problem, "target", target, batched=False)
    init = _check_init(problem, init)
    return _solve_jit(problem, target, _traced_floats(method), init, _key(key))


@eqx.filter_jit
def _solve_batch(problem, targets, method, keys):
    init = jnp.zeros(problem.n_blendshapes, problem.columns.dtype)
    return jax.vmap(lambda b, k: _solve_one(problem, b, method, init, k))(targets, keys)


@eqx.filter_jit
def _solve_warm(problem, targets, method, keys):
    def step(previous, frame):
        target, key = frame
        solution = _solve_one(problem, target, method, previous, key)
        return solution.weights, solution  # finite: a failed frame returns its start

    init = jnp.zeros(problem.n_blendshapes, problem.columns.dtype)
    _, solutions = jax.lax.scan(step, init, (targets, keys))
    return solutions


@eqx.filter_jit
def _solve_temporal(problem, targets, method, key):
    """A temporal method on the whole take: per-frame leaves like ``_solve_batch``."""
    dtype = problem.columns.dtype
    n, k = targets.shape[0], problem.n_blendshapes
    offsets = (targets - problem.neutral).reshape(n, -1)
    init = jnp.zeros((n, k), dtype)
    run = method.sequence(problem, offsets, init, key)
    per_frame = jax.vmap(lambda w, o: objective(problem, w, o, method.alpha))
    values = per_frame(run.weights, offsets)
    finite = jnp.all(jnp.isfinite(run.weights)) & jnp.all(jnp.isfinite(values))
    weights = jnp.where(finite, run.weights, init)
    values = jnp.where(finite, values, per_frame(init, offsets))
    owner = jnp.asarray(window_owner(n, method.window))
    history = run.history.reshape(-1, run.history.shape[-1])[owner]
    steps = jnp.atleast_1d(jnp.asarray(run.steps, jnp.int32))[owner]
    converged = jnp.atleast_1d(run.converged)[owner] & finite
    smoothness = method.smoothness_for(problem)
    smooth, speed = time_terms_per_frame(weights, smoothness, method.velocity)

    def frame(weights, value, history, steps, converged, smooth, speed):
        result = optx.RESULTS.where(
            finite,
            optx.RESULTS.where(converged, optx.RESULTS.successful, optx.RESULTS.max_steps_reached),
            optx.RESULTS.nonlinear_divergence,
        )
        stats = {"steps": steps, "converged": converged, "smoothness_term": smooth,
                 "velocity_term": speed}  # fmt: skip
        return Solution(weights=weights, objective=value, history=history, result=result,
                        stats=stats)  # fmt: skip

    return jax.vmap(frame)(weights, values, history, steps, converged, smooth, speed)


def solve_sequence(
    problem: InverseProblem | BlendshapeRig,
    targets: Float[ArrayLike, "T V 3"],
    method: AbstractInverseMethod,
    *,
    warm_start: bool = False,
    key: PRNGKeyArray | None = None,
    across_processes: bool = False,
) -> Solution:
    """Solve a whole take; returns a Solution whose leaves have a leading frame axis.

    Frames are independent and ``vmap``ped unless ``warm_start``, in which case each frame
    starts from the previous frame's weights (a ``scan``; a frame that fails returns its start,
    never NaN, so it cannot poison later frames). Warm starts can keep mutually exclusive
    shapes active across frames, as Racković et al. warn. Each frame gets its own key
    (``jax.random.split(key, T)``), so the ``random`` order draws a fresh permutation per
    frame and pass.

    A temporal method (``AbstractTemporalMethod``, e.g. ``TemporalNewton``) solves the take
    jointly instead (``warm_start`` must be False): ``objective[t]`` is still frame t's
    1/2 ||f(w_t) - b_t||^2 + alpha 1^T w_t, the time terms are in ``stats["smoothness_term"]``
    and ``stats["velocity_term"]`` (split over frames so that everything sums to the take's
    E), and ``history[t]`` is the whole take's E after each iteration (of the window that
    weighs frame t most, when the method solves windows).

    Compiled once per problem shape, take length and method type: later calls with other
    targets or another alpha reuse the compiled function. Every frame is checked first: a
    non-finite frame raises a ValueError listing the frames.

    ``across_processes`` (independent frames only): after ``canrig_jax.distributed.
    initialize``, the take is solved in chunks of ``FRAMES_PER_CALL`` frames, each process
    solving its contiguous run of chunks, and every process returns the whole take's Solution
    in frame order (``distributed.gather_frames``). The weights do not depend on the number
    of processes (bit for bit); they differ from a solve of all frames in one batch by
    float32 rounding only (a batched solve rounds differently with the batch's size).
    """
    _check_method(method)
    problem = _check_problem(problem)
    _check_bounds(problem, method)
    _check_target(problem, "targets", targets, batched=True)
    if not isinstance(warm_start, bool):
        raise TypeError(f"warm_start: expected a bool, got {warm_start!r}")
    if across_processes and (warm_start or isinstance(method, AbstractTemporalMethod)):
        raise ValueError(
            "across_processes: frames are shared over processes only when they are "
            "independent (warm_start=False and a per-frame method)"
        )
    targets = jnp.asarray(targets, problem.columns.dtype)
    method = _traced_floats(method)
    if isinstance(method, AbstractTemporalMethod):
        if warm_start:
            raise ValueError(
                "warm_start: a temporal method solves the take jointly; pass warm_start=False"
            )
        return _solve_temporal(problem, targets, method, _key(key))
    keys = jax.random.split(_key(key), targets.shape[0])
    run = _solve_warm if warm_start else _solve_batch
    if across_processes:
        from ..distributed import gather_frames

        return gather_frames(
            lambda tk: run(problem, tk[0], method, tk[1]), (targets, keys), chunk=FRAMES_PER_CALL
        )
    return run(problem, targets, method, keys)


FRAMES_PER_CALL = 32
"""Frames per compiled call when ``solve_sequence`` shares a take across processes."""


HISTORY_FRAMES = 2
"""Frames before a lagged ``Stream``'s window that enter its time terms, held fixed (the
second difference reaches two frames back)."""


def _lagged_one(problem, target, method, state, present_new, key) -> tuple[Solution, Any]:
    """One call of a lagged ``Stream``: the window (history, then lag + 1 frames) moves on by
    a frame, is solved jointly with the history held, and the Solution of its oldest solved
    frame comes back with the moved state. ``present_new`` False: no new frame (``flush``).
    The window keeps each frame's M^T o_t and ||o_t||^2, computed once as the frame enters,
    not its (3V,) offset o_t."""
    offset_sq, projections, weights, present, carry = state
    dtype = problem.columns.dtype
    offset = jnp.where(present_new, (jnp.asarray(target, dtype) - problem.neutral).reshape(-1), 0)
    offset_sq = jnp.concatenate([offset_sq[1:], (offset @ offset)[None]])
    projections = jnp.concatenate([projections[1:], (problem.columns @ offset)[None]])
    newest = jnp.where(present_new, weights[-1], 0.0)  # warm start from the last estimate
    weights = jnp.concatenate([weights[1:], newest[None]])
    present = jnp.concatenate([present[1:], jnp.asarray(present_new)[None]])
    held = (jnp.arange(weights.shape[0]) < HISTORY_FRAMES) | ~present
    run, carry = method.solve_window(
        problem,
        None,
        weights,
        held,
        present,
        projections,
        history=HISTORY_FRAMES,
        carry=method.shift_window_carry(carry),
        offset_sq=offset_sq,
    )
    finite = jnp.all(jnp.isfinite(run.weights))
    solved = jnp.where(finite, run.weights, weights)
    out = HISTORY_FRAMES  # the oldest solved frame: final after this call
    frame = Iterate(run.weights[out], run.history, run.steps, run.converged & finite)
    solution = _solution(problem, None, method, weights[out], frame, projections[out],
                         offset_sq[out])  # fmt: skip
    solved = solved.at[out].set(solution.weights)
    return solution, (offset_sq, projections, solved, present, carry)


def _plain_call(problem, method, warm_start, key, target, state):
    """One call of a ``Stream`` without ``lag``, keyed by its frame counter: the Solution and
    the next state (the weights and carry the next frame starts from; with ``warm_start``
    False, the same start every frame)."""
    init, carry, frame = state
    solution, moved = _stream_one(
        problem, target, method, init, jax.random.fold_in(key, frame), carry
    )
    if warm_start:
        init, carry = solution.weights, moved
    return solution, (init, carry, frame + 1)


def _lagged_call(problem, method, key, target, state, present_new, emit):
    """One call of a lagged ``Stream`` (``_lagged_one``), keyed by its frame counter; the
    Solution's ``stats["frame"]`` is the index of the next frame to return, which moves on
    when ``emit``."""
    window, frame, returned = state
    solution, window = _lagged_one(
        problem, target, method, window, present_new, jax.random.fold_in(key, frame)
    )
    stats = {**solution.stats, "frame": returned}
    solution = Solution(solution.weights, solution.objective, solution.history,
                        solution.result, stats)  # fmt: skip
    moved = (window, frame + present_new.astype(frame.dtype), returned + emit.astype(frame.dtype))
    return solution, moved


@functools.lru_cache(maxsize=64)
def _compiled_call(body, static, treedef, *options):
    """``body`` compiled once per (static part of the problem and method, the structure
    ``treedef`` of their array leaves, ``options``): a ``jax.jit`` of the array leaves alone,
    passed as a flat tuple, the state argument donated, so that a ``Stream`` call is one
    dispatch with no Python-side tree work (``eqx.filter_jit`` partitions its arguments on
    every call: ~0.3 ms, a tenth of the projection floor on ict-quartic; flattening the
    problem's Modules on every call, ~10 us)."""

    def call(leaves, key, target, state, *flags):
        problem, method = eqx.combine(jax.tree.unflatten(treedef, leaves), static)
        return body(problem, method, *options, key, target, state, *flags)

    call.__name__ = call.__qualname__ = f"stream{body.__name__}"  # in jax.log_compiles
    return jax.jit(call, donate_argnums=3)


def _check_lag(lag, method, warm_start) -> None:
    if lag is None:
        return
    if isinstance(lag, bool) or not isinstance(lag, int | np.integer) or lag < 0:
        raise ValueError(f"lag: expected None or a non-negative integer of frames, got {lag!r}")
    if not isinstance(method, AbstractTemporalMethod):
        raise ValueError(
            "lag: a lagged stream solves its last lag + 1 frames jointly with the time terms; "
            "expected a temporal method (an inverse.AbstractTemporalMethod such as "
            f"inverse.TemporalNewton), got {type(method).__name__}"
        )
    if method.window is not None:
        raise ValueError(
            f"window: a lagged stream solves its own window of lag + 1 frames; expected "
            f"TemporalNewton(window=None), got window={method.window}"
        )
    if warm_start is False:
        raise ValueError(
            "warm_start: a lagged stream starts each window from the previous one's weights; "
            "leave warm_start unset (or True) with lag"
        )


class Stream:
    """One-frame-at-a-time solving for live capture: ``prepare`` once, then one compiled call
    per frame, warm-started from the previous frame's weights when ``warm_start`` (weights
    are always finite: a failed frame returns its start). With ``warm_start`` the method's
    carry (``AbstractInverseMethod.step``) goes from frame to frame too: ``QuarticNewton``
    hands on its last Gauss-Newton matrix, which with ``refresh > 1`` the next frame starts
    from instead of recomputing it (about twice the time of the frame's projection, the
    floor of any one-frame solve: ``experiments/inverse_rig_streaming.py``).

        stream = inverse.Stream(problem, inverse.QuarticNewton(alpha=5.0, refresh=50),
                                warm_start=True)
        for mesh in capture:
            weights = stream(mesh).weights

    **Temporal streaming** (``lag=L`` with a temporal method such as ``TemporalNewton``):
    each call solves the last L + 1 frames jointly with the method's time terms, the
    ``HISTORY_FRAMES`` frames before them held at the weights already returned for them, and
    returns the Solution of the frame L calls back (``stats["frame"]`` its index), which is
    final from then on: weights come out L frames late (L / fps seconds) plus the call's own
    time. The first L calls return None (no frame is final yet); ``flush()`` returns the
    last L frames' Solutions at the end of a take and empties the stream. Frames of the
    window start from the previous call's weights (a lagged stream is always warm-started).
    ``lag=0`` solves the newest frame alone with the time terms against the two frames
    before it (a causal smoother, no delay).

        stream = inverse.Stream(problem, inverse.TemporalNewton(alpha=1.0), lag=2)
        solved = [s for s in map(stream, capture) if s is not None] + stream.flush()

    Frame t uses the key ``jax.random.fold_in(key, t)``.
    """

    def __init__(
        self,
        problem: InverseProblem | BlendshapeRig,
        method: AbstractInverseMethod,
        *,
        warm_start: bool | None = None,
        lag: int | None = None,
        key: PRNGKeyArray | None = None,
    ):
        _check_method(method)
        _check_lag(lag, method, warm_start)
        self.problem = _check_problem(problem)
        _check_bounds(self.problem, method)
        self.method = _traced_floats(method)
        self.lag = None if lag is None else int(lag)
        self.warm_start = bool(warm_start) or self.lag is not None
        self.key = _key(key)
        self.frame = 0
        dynamic, static = eqx.partition((self.problem, self.method), eqx.is_array)
        leaves, treedef = jax.tree.flatten(dynamic)
        self._leaves = tuple(leaves)
        if self.lag is None:
            self._call = _compiled_call(_plain_call, static, treedef, self.warm_start)
            init = jnp.zeros(self.problem.n_blendshapes, self.problem.columns.dtype)
            frame = jnp.asarray(0, jnp.int32)
            state = (init, self.method.initial_carry(self.problem), frame)
            self.state = jax.tree.map(jnp.array, state)  # own buffers: the state is donated
        else:
            self._call = _compiled_call(_lagged_call, static, treedef)
            self._flags = {flag: jnp.asarray(flag) for flag in (False, True)}
            self._empty_window(0)

    def _empty_window(self, frame: int) -> None:
        n = HISTORY_FRAMES + self.lag + 1
        dtype = self.problem.columns.dtype
        window = (
            jnp.zeros(n, dtype),
            jnp.zeros((n, self.problem.columns.shape[0]), dtype),
            jnp.zeros((n, self.problem.n_blendshapes), dtype),
            jnp.zeros(n, bool),
            self.method.initial_window_carry(self.problem, self.lag + 1),
        )
        # (window, next frame, next frame to return), in buffers of its own: it is donated
        counters = jnp.asarray(frame, jnp.int32), jnp.asarray(frame, jnp.int32)
        self.state = jax.tree.map(jnp.array, (window, *counters))
        self.pending = 0  # frames in the window not returned yet

    def __call__(self, target: Float[ArrayLike, "V 3"]) -> Solution | None:
        _check_target(self.problem, "target", target, batched=False)
        if self.lag is not None:
            return self._lagged(target, True)
        solution, self.state = self._call(self._leaves, self.key, target, self.state)
        self.frame += 1
        return solution

    def _lagged(self, target, present: bool, emit: bool = True) -> Solution | None:
        """Move the window on by one call; the Solution of the frame it finalises, or None
        while the frame it returns is not there yet."""
        if present:
            self.frame += 1
            self.pending += 1
            emit = self.pending > self.lag
        flags = self._flags[present], self._flags[emit]
        solution, self.state = self._call(self._leaves, self.key, target, self.state, *flags)
        if not emit:
            return None
        self.pending -= 1
        return solution

    def flush(self) -> list[Solution]:
        """A lagged stream's last frames (up to ``lag`` of them, in frame order): the window
        moves on with no new frames until every frame has been returned; the stream is then
        empty, ready for another take (frame numbers go on). Raises a ValueError without
        ``lag``."""
        if self.lag is None:
            raise ValueError("flush: only a lagged stream (Stream(..., lag=L)) holds frames back")
        neutral = self.problem.neutral
        # a take shorter than the lag: move its first frame to the returned slot first
        for _ in range(self.lag - self.pending if self.pending else 0):
            self._lagged(neutral, False, emit=False)
        out = []
        while self.pending:
            out.append(self._lagged(neutral, False))
        self._empty_window(self.frame)
        return out


__all__ = ["HISTORY_FRAMES", "Stream", "solve", "solve_sequence"]
