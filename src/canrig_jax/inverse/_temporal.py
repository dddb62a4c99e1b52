"""The temporal inverse rig: a whole take solved jointly, smooth in time (Racković et al. 2024).

Racković et al. (SIGGRAPH Asia 2024, "Refined inverse rigging") add a temporal smoothness
penalty to the L1-penalised objective of the 2023 paper and minimise over the weights of all
frames together. Over a take of T frames, offsets o_t = (b_t - b0).ravel() and weights
W = (w_1, ..., w_T) in [0, u]^{T x K}:

    E(W) = sum_t [1/2 ||f(w_t) - b_t||^2 + alpha 1^T w_t]
           + smoothness/2 sum_t ||w_{t-1} - 2 w_t + w_{t+1}||^2     (t = 2 .. T-1)
           + velocity/2   sum_t ||w_t - w_{t-1}||^2                  (t = 2 .. T)

``TemporalNewton`` minimises it by projected Gauss-Newton over all T K weights jointly, the
same iteration as ``QuarticNewton`` (see ``_projected_newton.py``: gradient, epsilon-active
set, Gauss-Newton step on the free weights, projected line search) with

- gradient: G_t (Q a_t - p_t) + alpha + smoothness (D^T D W)_t + velocity (D1^T D1 W)_t,
  D (T-2 x T) the second-difference and D1 (T-1 x T) the first-difference matrix;
- Gauss-Newton matrix: blockdiag(G_t Q G_t^T) + smoothness D^T D (x) I_K
  + velocity D1^T D1 (x) I_K, block-banded with block bandwidth 2 in time.

The system is solved in O(T K^3) by ``block_banded_solve``: consecutive frames are paired into
2K x 2K blocks, which makes it block-tridiagonal, and a block Cholesky (block Thomas) runs over
the pairs in a ``lax.scan`` with one Cholesky factor and two triangular solves per pair
(``canrig_jax._linalg``: one matrix per LAPACK call, so batched windows cannot deadlock). The
dense (T K)^2 matrix is never formed.

One frame alone has no time terms, so ``TemporalNewton.__call__`` (what ``solve`` uses) takes
the same steps as ``QuarticNewton`` at the same settings. ``solve_sequence`` calls
``TemporalNewton.sequence`` on the whole take (or on overlapping windows, see
``window_starts`` and ``stitch_windows``).
"""

import abc
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Float64, Int, Int64, PRNGKeyArray

from .._checks import is_concrete
from .._linalg import cholesky, solve_triangular, spd_solve
from ..rig import UNIT_IN_CM
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

DEFAULT_SMOOTHNESS_CM2 = 100.0
"""``TemporalNewton``'s default smoothness (cm^2; ``smoothness_for`` converts it to a rig's
units): the value the rule in ``experiments/results/inverse_rig/RULE_temporal.md`` chose on
held-out real capture (the data folder's Live Link Face take driving the ict-quartic rig, with
noise of variance 0.03 cm^2: the lowest mean RMSE on the take's first half, frames 0-89), as
recorded in ``experiments/results/inverse_rig/results.json`` (``temporal_protocol.ict.
smoothness_cm2``)."""

# ---------------------------------------------------------------------------------------------
# time-difference operators


def difference_bands(n_frames: int, order: int) -> Float64[np.ndarray, "3 T"]:
    """(3, T) bands of Delta^T Delta for the ``order``-th difference matrix Delta ((T - order)
    x T): row 0 the diagonal, row 1 the entries (t, t + 1), row 2 the entries (t, t + 2)
    (zero past the end, and zero for row 2 when ``order`` is 1). Host-side: T is static."""
    stencil = {1: np.array([-1.0, 1.0]), 2: np.array([1.0, -2.0, 1.0])}[order]
    bands = np.zeros((3, n_frames))
    for row in range(n_frames - order):
        for i, ci in enumerate(stencil):
            for j, cj in enumerate(stencil[i:], start=i):
                bands[j - i, row + i] += ci * cj
    return bands


def second_difference(weights: Float[Array, "T K"]) -> Float[Array, "_S K"]:
    """w_{t-1} - 2 w_t + w_{t+1} for t = 1 .. T-2 (zero rows for T < 3)."""
    return weights[:-2] - 2.0 * weights[1:-1] + weights[2:]


def _second_difference_adjoint(d: Float[Array, "S K"], n_frames: int) -> Float[Array, "T K"]:
    out = jnp.zeros((n_frames, d.shape[1]), d.dtype)
    return out.at[:-2].add(d).at[1:-1].add(-2.0 * d).at[2:].add(d)


def _first_difference_adjoint(d: Float[Array, "S K"], n_frames: int) -> Float[Array, "T K"]:
    out = jnp.zeros((n_frames, d.shape[1]), d.dtype)
    return out.at[1:].add(d).at[:-1].add(-d)


def time_penalty(weights: Float[Array, "T K"], smoothness: Any, velocity: Any) -> Float[Array, ""]:
    """smoothness/2 ||D W||^2 + velocity/2 ||D1 W||^2 over a take."""
    d2 = second_difference(weights)
    d1 = jnp.diff(weights, axis=0)
    return 0.5 * smoothness * jnp.sum(d2 * d2) + 0.5 * velocity * jnp.sum(d1 * d1)


def weighted_difference_bands(
    row_weights: Float[Array, " R"], n_frames: int, order: int
) -> Float[Array, "3 T"]:
    """``difference_bands`` of Delta^T diag(c) Delta, each row of the ``order``-th difference
    matrix Delta weighted by ``row_weights`` c ((T - order,), traced); all ones gives
    ``difference_bands``. A row with weight 0 drops out of the time terms (a frame that is
    not there yet, in a lagged ``Stream``)."""
    stencil = {1: (-1.0, 1.0), 2: (1.0, -2.0, 1.0)}[order]
    rows = n_frames - order
    bands = jnp.zeros((3, n_frames), row_weights.dtype)
    if rows <= 0:
        return bands
    for i, ci in enumerate(stencil):
        for j, cj in enumerate(stencil[i:], start=i):
            bands = bands.at[j - i, i : i + rows].add(ci * cj * row_weights)
    return bands


def _weighted_time_penalty(weights, smoothness, velocity, rows2, rows1):
    """``time_penalty`` with each difference row weighted (``weighted_difference_bands``)."""
    d2 = second_difference(weights)
    d1 = jnp.diff(weights, axis=0)
    return 0.5 * smoothness * jnp.sum(rows2[:, None] * d2 * d2) + 0.5 * velocity * jnp.sum(
        rows1[:, None] * d1 * d1
    )


def time_terms_per_frame(
    weights: Float[Array, "T K"], smoothness: Any, velocity: Any
) -> tuple[Float[Array, " T"], Float[Array, " T"]]:
    """The time terms split over frames so that they sum to ``time_penalty``: frame t gets
    smoothness/2 ||w_{t-1} - 2 w_t + w_{t+1}||^2 (0 at both ends) and
    velocity/2 ||w_t - w_{t-1}||^2 (0 at the first frame)."""
    n = weights.shape[0]
    d2 = jnp.sum(second_difference(weights) ** 2, axis=1)
    d1 = jnp.sum(jnp.diff(weights, axis=0) ** 2, axis=1)
    smooth = jnp.zeros(n, weights.dtype).at[1:-1].set(0.5 * smoothness * d2)
    speed = jnp.zeros(n, weights.dtype).at[1:].set(0.5 * velocity * d1)
    return smooth, speed


# ---------------------------------------------------------------------------------------------
# the block-banded solve


def block_tridiagonal_solve(
    diagonal: Float[Array, "n m m"],
    lower: Float[Array, "_n1 m m"],
    rhs: Float[Array, "n m"],
) -> Float[Array, "n m"]:
    """x with A x = rhs for a symmetric positive definite block-tridiagonal A: diagonal blocks
    A_jj = ``diagonal[j]``, A_{j+1,j} = ``lower[j]`` (A_{j,j+1} its transpose).

    Block Cholesky in one forward scan (L_j L_j^T = A_jj - C_j C_j^T, C_j = A_{j,j-1}
    L_{j-1}^-T, y_j = L_j^-1 (r_j - C_j y_{j-1})) and one backward scan
    (x_j = L_j^-T (y_j - C_{j+1}^T x_{j+1})): O(n m^3), NaN where A is not positive definite
    (as ``_linalg.cholesky``)."""
    m = diagonal.shape[1]
    first = cholesky(diagonal[0])
    y0 = solve_triangular(first, rhs[0])

    def forward(carry, block):
        previous, y_previous = carry
        a, b, r = block
        c = solve_triangular(previous, b.T).T  # B L^-T: (L^-1 B^T)^T
        factor = cholesky(a - c @ c.T)
        y = solve_triangular(factor, r - c @ y_previous)
        return (factor, y), (factor, c, y)

    _, (factors, couplings, ys) = jax.lax.scan(forward, (first, y0), (diagonal[1:], lower, rhs[1:]))
    factors = jnp.concatenate([first[None], factors])
    ys = jnp.concatenate([y0[None], ys])
    factors, ys = jax.lax.optimization_barrier((factors, ys))
    x_last = solve_triangular(factors[-1], ys[-1], transpose=True)

    def backward(x_next, block):
        factor, c_next, y = block
        x = solve_triangular(factor, y - c_next.T @ x_next, transpose=True)
        return x, x

    _, xs = jax.lax.scan(backward, x_last, (factors[:-1], couplings, ys[:-1]), reverse=True)
    return jnp.concatenate([xs, x_last[None]]).reshape(-1, m)


def block_banded_solve(
    band0: Float[Array, "T K K"],
    band1: Float[Array, "_T1 K K"],
    band2: Float[Array, "_T2 K K"],
    rhs: Float[Array, "T K"],
) -> Float[Array, "T K"]:
    """x with H x = rhs for a symmetric positive definite H of block bandwidth 2:
    H_{t,t} = ``band0[t]``, H_{t+1,t} = ``band1[t]``, H_{t+2,t} = ``band2[t]``.

    Consecutive frames are paired into 2K blocks (a last unpaired frame gets an identity
    partner), which makes H block-tridiagonal; ``block_tridiagonal_solve`` does the rest."""
    n, k = rhs.shape
    if n == 1:
        return block_tridiagonal_solve(band0, band1[:0], rhs)
    if n % 2:  # pad with a decoupled identity frame
        band0 = jnp.concatenate([band0, jnp.eye(k, dtype=band0.dtype)[None]])
        band1 = jnp.concatenate([band1, jnp.zeros((1, k, k), band1.dtype)])
        band2 = jnp.concatenate([band2, jnp.zeros((1, k, k), band2.dtype)])
        rhs = jnp.concatenate([rhs, jnp.zeros((1, k), rhs.dtype)])
    pairs = rhs.shape[0] // 2
    even, odd = band0[0::2], band0[1::2]
    inner = band1[0::2]  # H_{2j+1, 2j}
    diagonal = jnp.concatenate(
        [
            jnp.concatenate([even, jnp.swapaxes(inner, 1, 2)], axis=2),
            jnp.concatenate([inner, odd], axis=2),
        ],
        axis=1,
    )
    # block (pair j+1, pair j): [[H(2j+2, 2j), H(2j+2, 2j+1)], [0, H(2j+3, 2j+1)]]
    across = band1[1::2]  # H_{2j+2, 2j+1}
    zero = jnp.zeros((pairs - 1, k, k), rhs.dtype)
    lower = jnp.concatenate(
        [
            jnp.concatenate([band2[0::2], across], axis=2),
            jnp.concatenate([zero, band2[1::2]], axis=2),
        ],
        axis=1,
    )
    # materialise the paired blocks: fused into the scan, XLA rebuilt them at every step (4x)
    diagonal, lower = jax.lax.optimization_barrier((diagonal, lower))
    x = block_tridiagonal_solve(diagonal, lower, rhs.reshape(pairs, 2 * k))
    return x.reshape(-1, k)[:n]


DENSE_WINDOW = 320
"""A system of at most this many weights (solved frames x K) is assembled densely and solved
by one Cholesky (``dense_banded_solve``) instead of ``block_banded_solve``'s scan over frame
pairs: a lagged ``Stream``'s window (lag + 1 frames) always is, a take rarely."""


def dense_banded_solve(
    band0: Float[Array, "T K K"],
    band1: Float[Array, "_T1 K K"],
    band2: Float[Array, "_T2 K K"],
    rhs: Float[Array, "T K"],
) -> Float[Array, "T K"]:
    """``block_banded_solve``'s system assembled as one dense (T K, T K) matrix and solved by
    one Cholesky factorisation (one LAPACK call; for a few frames, faster than the scan)."""
    n, k = rhs.shape
    zero = jnp.zeros((k, k), rhs.dtype)

    def block(row: int, col: int):
        """H_{row, col}: a band below the diagonal, its transpose above, zero past band 2."""
        if row < col:
            return block(col, row).T
        return (band0, band1, band2)[row - col][col] if row - col <= 2 else zero

    # one concatenation of the (T, T) blocks: no chain of updates of a (T K)^2 matrix
    matrix = jnp.block([[block(row, col) for col in range(n)] for row in range(n)])
    return spd_solve(matrix, rhs.reshape(-1)).reshape(n, k)


# ---------------------------------------------------------------------------------------------
# windows


def window_starts(n_frames: int, window: int) -> Int64[np.ndarray, " n"]:
    """First frames of the overlapping windows covering a take: hop = window // 2, the last
    window ending at the take's last frame; one window (the whole take) when T <= window."""
    if n_frames <= window:
        return np.zeros(1, np.int64)
    hop = max(window // 2, 1)
    count = -(-(n_frames - window) // hop) + 1
    return np.minimum(np.arange(count) * hop, n_frames - window)


def window_taper(window: int) -> Float64[np.ndarray, " W"]:
    """(window,) positive tent weights min(j + 1, window - j) used to blend windows."""
    j = np.arange(window)
    return np.minimum(j + 1, window - j).astype(np.float64)


def stitch_windows(
    values: Float[Array, "n W *rest"], starts: Int64[np.ndarray, " n"], n_frames: int
) -> Float[Array, " T *rest"]:
    """Blend per-window results into a take: frame t is the average of the windows holding it,
    weighted by ``window_taper`` (a convex combination, so weights stay in the box; frames
    held by one window take its value)."""
    window = values.shape[1]
    taper = jnp.asarray(window_taper(window), values.dtype)
    frames = jnp.asarray(starts)[:, None] + jnp.arange(window)[None, :]  # (n, W)
    shape = (-1, window) + (1,) * (values.ndim - 2)
    mass = jnp.zeros(n_frames, values.dtype).at[frames].add(jnp.broadcast_to(taper, frames.shape))
    total = jnp.zeros((n_frames, *values.shape[2:]), values.dtype)
    total = total.at[frames].add(values * taper.reshape(shape))
    return total / mass.reshape((-1,) + (1,) * (values.ndim - 2))


def _window_owner(starts: np.ndarray, window: int, n_frames: int) -> np.ndarray:
    """(T,) for each frame, the window whose taper weighs it most."""
    taper = window_taper(window)
    weight = np.full((len(starts), n_frames), -1.0)
    for i, s in enumerate(starts):
        weight[i, s : s + window] = taper
    return np.argmax(weight, axis=0)


# ---------------------------------------------------------------------------------------------
# methods


class AbstractTemporalMethod(AbstractInverseMethod):
    """An inverse-rig method that solves a take jointly: ``solve_sequence`` calls its
    ``sequence`` instead of solving frames one by one, and a ``Stream`` with ``lag`` calls its
    ``solve_window`` on the last frames.

    Attributes:
        smoothness: weight of the second-difference penalty (>= 0), or None for the default
            (``DEFAULT_SMOOTHNESS_CM2`` in the rig's units, ``smoothness_for``).
        velocity: weight of the first-difference penalty (>= 0).
        window: None to solve the whole take at once, else the length of the overlapping
            windows solved in a batch and blended.
    """

    smoothness: eqx.AbstractVar[float | None]
    velocity: eqx.AbstractVar[float]
    window: eqx.AbstractVar[int | None]

    def smoothness_for(self, problem: InverseProblem) -> Any:
        """The smoothness in the problem's squared rig units: ``smoothness``, or when it is
        None ``DEFAULT_SMOOTHNESS_CM2`` divided by (cm per rig unit)^2."""
        if self.smoothness is not None:
            return self.smoothness
        return DEFAULT_SMOOTHNESS_CM2 / UNIT_IN_CM[problem.rig.units] ** 2

    @abc.abstractmethod
    def sequence(
        self,
        problem: InverseProblem,
        offsets: Float[Array, "T N"],
        init: Float[Array, "T K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        """Solve a take; offsets (T, 3V) = b_t - b0 flattened. Returns an ``Iterate`` with
        (T, K) weights and the whole take's E after each iteration as history."""

    @abc.abstractmethod
    def solve_window(
        self,
        problem: InverseProblem,
        offsets: Float[Array, "W N"] | None,
        init: Float[Array, "W K"],
        held: Bool[Array, " W"],
        present: Bool[Array, " W"],
        projections: Float[Array, "W P"] | None = None,
        history: int = 0,
        carry: Any = None,
        offset_sq: Float[Array, " W"] | None = None,
    ) -> tuple[Iterate, Any]:
        """Solve a window of frames jointly with some of them held: frames with ``held``
        keep their ``init`` weights (they enter the time terms as constants, their data terms
        are left out), frames not ``present`` drop out of the time terms too (every
        difference row touching one is left out). ``projections``: the frames' M^T o_t when
        the caller carries them; ``history`` (static): the first frames, held, whose data
        terms are not computed at all; ``carry``: what the previous window's solve handed on
        (``initial_window_carry``, then moved on by ``shift_window_carry``), None for nothing;
        ``offset_sq``: the frames' ||o_t||^2 when the caller carries them. With both
        ``projections`` and ``offset_sq`` the offsets themselves are not read (None will do:
        a lagged ``Stream`` keeps no (W, 3V) window). Returns the window's (W, K) weights and
        the carry for the next window."""

    def initial_window_carry(self, problem: InverseProblem, n_solved: int) -> Any:
        """The carry of an empty window of ``n_solved`` solved frames (None: nothing)."""
        return None

    def shift_window_carry(self, carry: Any) -> Any:
        """The carry moved on by one frame, as the window moves on (None: nothing)."""
        return carry


def _check_nonnegative(name: str, value: Any) -> None:
    if value is not None and is_concrete(value) and not (0 <= value < float("inf")):
        raise ValueError(f"{name}: expected a non-negative, finite weight, got {value}")


STREAM_BLOCKS = ("exact", "on_entry")
"""``TemporalNewton.stream_blocks``: how a lagged ``Stream``'s window gets its Gauss-Newton
blocks (see the attribute)."""

STREAM_STEPS = ("newton_first", "searched")
"""``TemporalNewton.stream_steps``: how a lagged ``Stream``'s window steps (see the
attribute)."""

WindowCarry = tuple[Float[Array, "S K K"], Bool[Array, ""]]
"""What ``TemporalNewton`` hands from one window of a lagged ``Stream`` to the next: the solved
frames' Gauss-Newton blocks G_t Q G_t^T (at the weights where they were last computed) and
whether they were carried from a previous solve (False: zeros, compute them first)."""


class TemporalNewton(AbstractTemporalMethod):
    """Projected Gauss-Newton on the temporal objective E(W) of a whole take (see the module
    docstring), with a block-banded O(T K^3) system solve.

    Attributes:
        alpha: L1 weight (>= 0), squared rig units (cm^2 for ICT), as ``QuarticNewton``.
        smoothness: weight of smoothness/2 sum_t ||w_{t-1} - 2 w_t + w_{t+1}||^2 (>= 0;
            squared rig units, since the weights are unitless). None (the default) takes
            ``DEFAULT_SMOOTHNESS_CM2`` converted to the rig's units (``smoothness_for``): the
            value chosen on held-out real capture (the data folder's Live Link Face take on
            the ict-quartic rig, lowest RMSE on its first half; the rule is
            ``experiments/results/inverse_rig/RULE_temporal.md``). 0 solves frames
            independently.
        velocity: weight of velocity/2 sum_t ||w_t - w_{t-1}||^2 (>= 0).
        window: None solves the whole take as one problem; an integer >= 3 solves
            overlapping windows of that many frames (hop window // 2) batched with
            ``jax.vmap``, each a whole-take problem of its own, and blends them
            (``stitch_windows``).
        iterations: cap on the Newton iterations.
        tol: stop when an iteration lowers E by less than ``tol`` relative to E.
        line_steps: step lengths tried per iteration (1, 1/2, ..., 2^-(line_steps - 1)).
        upper: upper bound of the box (1 in the paper).
        refresh: the Gauss-Newton blocks G_t Q G_t^T (the (T K) x P x P product of an
            iteration, most of its cost) are recomputed every ``refresh`` iterations and
            reused in between (chord steps: still descent directions, the line search still
            only accepts decreases); an iteration that gains less than ``tol`` on reused
            blocks recomputes them before the solve may stop, so the stopping test is always
            passed on fresh ones (``QuarticNewton``'s rule). With ``stream_blocks="exact"``
            a lagged ``Stream`` also carries them from window to window. 1 (default)
            recomputes them every iteration; under ``vmap`` (``window``) they are
            recomputed every iteration.
        stream_blocks: a lagged ``Stream``'s Gauss-Newton blocks. ``"on_entry"`` (default):
            each frame's block is computed once, when the frame enters the window (at the
            weights it starts from, the previous frame's), and carried with the window while
            the frame is in it; every step of every window uses them (chord steps), and the
            solve stops on them (the gradient and line search are exact, so it stops where
            an iteration gains less than ``tol``): one K x P x P product per frame instead of
            one per solved frame and iteration. About 1.7x faster per frame on ict-quartic at
            lag 2, with the same RMSE and roughness within 0.1 %
            (``experiments/results/inverse_rig/results.json``, ``temporal``). ``"exact"``:
            ``refresh``'s rule in each window (every block recomputed every iteration at
            ``refresh=1``). One frame, a take and windowed takes are unaffected.
        stream_steps: a lagged ``Stream``'s step lengths. ``"newton_first"`` (default): the
            full Newton step is scored alone and taken when it lowers E enough (``ARMIJO``,
            Armijo's rule); only when it does not are the ``line_steps`` lengths scored and
            the best taken. One trial instead of ``line_steps`` in almost every iteration
            (each trial is a (frames x P) x P product), for a few more iterations: the
            stream's RMSE and roughness on the Live Link take match ``"searched"`` to about
            4 digits (``experiments/results/inverse_rig/results.json``, ``temporal``).
            ``"searched"``: every length scored in every iteration, the lowest taken (the
            iteration of a take). One frame, a take and windowed takes always search.
    """

    alpha: float = 0.0
    smoothness: float | None = None
    velocity: float = 0.0
    window: int | None = eqx.field(static=True, default=None)
    iterations: int = eqx.field(static=True, default=100)
    tol: float = 1e-5
    line_steps: int = eqx.field(static=True, default=6)
    upper: float = 1.0
    refresh: int = eqx.field(static=True, default=1)
    stream_blocks: str = eqx.field(static=True, default="on_entry")
    stream_steps: str = eqx.field(static=True, default="newton_first")
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        check_alpha(self.alpha)
        check_count("refresh", self.refresh)
        if self.stream_blocks not in STREAM_BLOCKS:
            raise ValueError(
                f"stream_blocks: expected one of {STREAM_BLOCKS}, got {self.stream_blocks!r}"
            )
        if self.stream_steps not in STREAM_STEPS:
            raise ValueError(
                f"stream_steps: expected one of {STREAM_STEPS}, got {self.stream_steps!r}"
            )
        _check_nonnegative("smoothness", self.smoothness)
        _check_nonnegative("velocity", self.velocity)
        if self.window is not None and (
            isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 3
        ):
            raise ValueError(f"window: expected None or an integer >= 3, got {self.window!r}")
        check_count("iterations", self.iterations)
        check_count("line_steps", self.line_steps)
        check_upper(self.upper)
        check_tol(self.tol)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        """One frame: no time terms, the steps of ``QuarticNewton``."""
        run, _ = self._take(problem, offset[None], init[None])
        return Iterate(run.weights[0], run.history, run.steps, run.converged)

    def sequence(
        self,
        problem: InverseProblem,
        offsets: Float[Array, "T N"],
        init: Float[Array, "_T K"],  # checked against offsets below, naming the argument
        key: PRNGKeyArray,
    ) -> Iterate:
        """Solve a take (whole, or in windows when ``window`` is set). ``init`` (T, K) is
        clipped to the box. Returns (T, K) weights; with windows, ``history`` (n, iterations)
        and ``steps``/``converged`` (n,) are per window (``window_starts``)."""
        n_coords = problem.columns.shape[1]
        k = problem.n_blendshapes
        if offsets.ndim != 2 or offsets.shape[1] != n_coords or offsets.shape[0] < 1:
            raise ValueError(f"offsets: expected shape (T, {n_coords}), got {offsets.shape}")
        if init.shape != (offsets.shape[0], k):
            raise ValueError(f"init: expected shape ({offsets.shape[0]}, {k}), got {init.shape}")
        init = jnp.clip(init, 0.0, self.upper)
        n = offsets.shape[0]
        if self.window is None or n <= self.window:
            return self._take(problem, offsets, init)[0]
        starts = window_starts(n, self.window)
        frames = starts[:, None] + np.arange(self.window)[None, :]
        runs = jax.vmap(lambda o, w: self._take(problem, o, w)[0])(offsets[frames], init[frames])
        weights = stitch_windows(runs.weights, starts, n)
        return Iterate(weights, runs.history, runs.steps, runs.converged)

    def solve_window(
        self,
        problem: InverseProblem,
        offsets: Float[Array, "W N"] | None,
        init: Float[Array, "W K"],
        held: Bool[Array, " W"],
        present: Bool[Array, " W"],
        projections: Float[Array, "W P"] | None = None,
        history: int = 0,
        carry: WindowCarry | None = None,
        offset_sq: Float[Array, " W"] | None = None,
    ) -> tuple[Iterate, WindowCarry]:
        """The window's E (held frames' data terms left out, difference rows touching an
        absent frame left out) minimised over the frames not ``held``, the same iteration as
        ``sequence`` (which is this with nothing held and every frame present). With
        ``refresh > 1`` and a ``carry``, the first iteration steps with the carried
        Gauss-Newton blocks (``shift_window_carry``: each frame's from the previous window,
        the newest frame's from the frame before it, whose weights it starts from)."""
        init = jnp.clip(init, 0.0, self.upper)
        if self.refresh == 1 and self.stream_blocks == "exact":
            carry = None  # every iteration computes the blocks: nothing to start from
        newton_first = self.stream_steps == "newton_first"
        return self._take(problem, offsets, init, held, present, projections, history, carry,
                          newton_first, offset_sq)  # fmt: skip

    def initial_window_carry(self, problem: InverseProblem, n_solved: int) -> WindowCarry:
        """(n_solved, K, K) zero blocks, not carried (the first iteration computes them)."""
        k = problem.n_blendshapes
        return jnp.zeros((n_solved, k, k), problem.gram.dtype), jnp.asarray(False)

    def shift_window_carry(self, carry: WindowCarry) -> WindowCarry:
        """The oldest solved frame's block dropped (it is final), the newest frame's block a
        copy of the frame before it (the weights it starts from)."""
        blocks, carried = carry
        return jnp.concatenate([blocks[1:], blocks[-1:]]), carried

    def _take(
        self,
        problem,
        offsets,
        init,
        held_frames=None,
        present=None,
        projections=None,
        history=0,
        carry=None,
        newton_first=False,
        offset_sq=None,
    ) -> tuple[Iterate, WindowCarry]:
        """The iteration. ``history`` (static): that many first frames are held and only enter
        the time terms (their data terms are not computed at all); ``projections`` (T, P):
        M^T o_t when the caller has them already; ``carry``: the solved frames' Gauss-Newton
        blocks to start from (``WindowCarry``), None to compute them; ``newton_first``
        (static): each step tries the full Newton step first (``_newton_first``), else the
        line search over every length; ``offset_sq`` (T,): ||o_t||^2 when the caller has them
        (then, with ``projections``, ``offsets`` is not read). Returns the Iterate and the
        blocks last computed."""
        terms = _take_terms(
            self, problem, offsets, held_frames, present, projections, history, offset_sq
        )
        on_entry = carry is not None and self.stream_blocks == "on_entry"

        def iteration(state):
            i, weights, value, gain, history, blocks, age, (a, residual) = state
            grad = _gradient(terms, weights, residual)
            blocks, age = self._blocks(terms, weights, value, gain, blocks, age, on_entry)
            step = _newton_step(terms, weights, grad, blocks)
            if newton_first:
                weights, gain, fit = _newton_first(
                    terms, weights, step, a, residual, grad, self.line_steps
                )
            else:
                weights, gain, fit = _line_search(
                    terms, weights, step, a, residual, self.line_steps
                )
            value = value - gain
            return i + 1, weights, value, gain, history.at[i].set(value), blocks, age, fit

        def keep_going(state):
            i, _, value, gain, _, _, age, _ = state
            fresh = jnp.asarray(True) if on_entry else age <= 1
            stop = _small_gain(gain, value, self.tol) & fresh
            return (i < self.iterations) & ((i == 0) | ~stop)

        value0 = _take_value(terms, init)
        history0 = jnp.zeros(self.iterations, terms.dtype)
        blocks0, age0 = self._initial_blocks(terms, init, carry, on_entry)
        gain0 = jnp.asarray(jnp.inf, terms.dtype)
        fit0 = _residuals(terms, init)
        state = (jnp.asarray(0), init, value0, gain0, history0, blocks0, age0, fit0)
        i, weights, value, gain, history, blocks, age, _ = jax.lax.while_loop(
            keep_going, iteration, state
        )
        history = jnp.where(jnp.arange(self.iterations) < i, history, value)
        converged = _small_gain(gain, value, self.tol) & ((age == 1) | on_entry)
        return Iterate(weights, history, i, converged), (blocks, jnp.asarray(True))

    def _blocks(self, terms, weights, value, gain, blocks, age, on_entry):
        """The solved frames' Gauss-Newton blocks for this iteration and their age:
        recomputed every ``refresh`` iterations and before the solve may stop
        (``QuarticNewton``'s rule), carried in between; with ``on_entry`` the carried blocks
        throughout (computed as each frame entered); under vmap every iteration."""
        stale = (age >= self.refresh) | _small_gain(gain, value, self.tol)
        if on_entry:
            stale = jnp.asarray(False)
        stale = _one_frame_or_batch(stale, jnp.asarray(True))
        blocks = jax.lax.cond(stale, lambda: _solved_blocks(terms, weights), lambda: blocks)
        return blocks, jnp.where(stale, 1, age + 1)

    def _initial_blocks(self, terms, init, carry, on_entry):
        """(blocks, age) the iteration starts from: nothing carried, the first iteration
        computes them; ``on_entry``, the newest frame's block at its start and the others
        carried (all computed when nothing was carried yet); else the carried blocks."""
        n, k = init.shape
        if carry is None:
            zeros = jnp.zeros((n - terms.history, k, k), terms.dtype)
            return zeros, jnp.asarray(self.refresh)
        blocks, carried = carry
        if on_entry:
            blocks = jax.lax.cond(
                carried,
                lambda: blocks.at[-1].set(_frame_blocks(terms.problem, init[-1:])[0]),
                lambda: _solved_blocks(terms, init),
            )
            return blocks, jnp.asarray(1)
        return blocks, jnp.where(carried, 1, self.refresh)


# ---------------------------------------------------------------------------------------------
# the iteration of a take (``TemporalNewton._take``), in named steps


class _TakeTerms(NamedTuple):
    """What every iteration of one take's solve reads: the problem, the frames' projections
    M^T o_t and squared norms ||o_t||^2, which frames are held (``held``) or solved, the
    difference rows that count (``rows2``, ``rows1``: all their frames present, one of them
    solved), the (3, T) bands of the time matrix, the weights of the terms, and ``history``
    (static) first frames held with no data terms."""

    problem: InverseProblem
    projections: Float[Array, "T P"]
    offset_sq: Float[Array, " T"]
    held: Bool[Array, " T"]
    solved: Bool[Array, " T"]
    rows2: Float[Array, " _T2"]
    rows1: Float[Array, " _T1"]
    bands: Float[Array, "3 T"]
    alpha: Any
    upper: Any
    smoothness: Any
    velocity: Any
    history: int

    @property
    def dtype(self):
        return self.problem.gram.dtype


def _take_terms(
    method, problem, offsets, held, present, projections, history, offset_sq=None
) -> _TakeTerms:
    """``_TakeTerms`` of a take (``held`` None: nothing held; ``present`` None: every frame
    there; ``projections`` and ``offset_sq`` None: computed from ``offsets``)."""
    gram = problem.gram
    n = offsets.shape[0] if projections is None else projections.shape[0]
    if held is None:
        held = jnp.zeros(n, bool)
    if present is None:
        present = jnp.ones(n, bool)
    # a difference row counts when all its frames are there and one of them is solved
    solved = ~held
    rows2 = (present[:-2] & present[1:-1] & present[2:]) & (solved[:-2] | solved[1:-1] | solved[2:])
    rows1 = (present[:-1] & present[1:]) & (solved[:-1] | solved[1:])
    rows2, rows1 = rows2.astype(gram.dtype), rows1.astype(gram.dtype)
    if projections is None:
        projections = offsets @ problem.columns.T  # (T, P) rows p_t = M^T o_t
    if offset_sq is None:
        offset_sq = jax.vmap(lambda o: o @ o)(offsets)  # (T,) ||o_t||^2
    smoothness, velocity = method.smoothness_for(problem), method.velocity
    second = weighted_difference_bands(rows2, n, 2)
    first = weighted_difference_bands(rows1, n, 1)
    bands = smoothness * second + velocity * first  # (3, T) of the time matrix
    return _TakeTerms(problem, projections, offset_sq, held, solved, rows2, rows1, bands,
                      method.alpha, method.upper, smoothness, velocity, history)  # fmt: skip


def _time_gradient(terms: _TakeTerms, weights: Float[Array, "T K"]) -> Float[Array, "T K"]:
    """The gradient of the (row-weighted) time terms."""
    n = weights.shape[0]
    d2 = terms.rows2[:, None] * second_difference(weights)
    g = terms.smoothness * _second_difference_adjoint(d2, n)
    d1 = terms.rows1[:, None] * jnp.diff(weights, axis=0)
    return g + terms.velocity * _first_difference_adjoint(d1, n)


def _take_value(terms: _TakeTerms, weights) -> Float[Array, ""]:
    """E at ``weights``: the solved frames' data terms (the history's left out) and the
    counted time terms."""
    h, problem = terms.history, terms.problem
    data = jax.vmap(lambda w, p, o_sq: problem.objective(w, p, o_sq, terms.alpha))(
        weights[h:], terms.projections[h:], terms.offset_sq[h:]
    )
    return jnp.sum(jnp.where(terms.held[h:], 0.0, data)) + _weighted_time_penalty(
        weights, terms.smoothness, terms.velocity, terms.rows2, terms.rows1
    )


def _frame_blocks(problem: InverseProblem, rows: Float[Array, "S K"]) -> Float[Array, "S K K"]:
    """(S, K, K) Gauss-Newton blocks G_t Q G_t^T at (S, K) weights: one S K x P x P product,
    Q G_t^T and then G_t (Q G_t^T) (the gram is small enough to stay in cache; a product over
    each weight's support streamed ``support_gram``, 10x the gram, and was slower; G_t Q first
    was about 15 % slower on MakeHuman's one-frame block)."""
    gram = problem.gram
    jacobian = jax.vmap(problem.jacobian)(rows)  # (S, K, P)
    gram_jacobian = gram @ jnp.swapaxes(jacobian, 1, 2)  # (S, P, K) Q G_t^T
    return jnp.matmul(jacobian, gram_jacobian)


def _solved_blocks(terms: _TakeTerms, weights) -> Float[Array, "S K K"]:
    """The solved frames' (all but the history's) Gauss-Newton blocks."""
    return _frame_blocks(terms.problem, weights[terms.history :])


def _residuals(terms: _TakeTerms, weights):
    """(a, residual) at ``weights``: the solved frames' coefficients a_t (no data terms in
    the history) and their residuals Q a_t - p_t. The iteration computes them at its start
    and then carries them from step to step (``_decreases`` has both at every trial)."""
    problem, h = terms.problem, terms.history
    a = jax.vmap(problem.coefficients)(weights[h:])  # (T - h, P)
    return a, a @ problem.gram - terms.projections[h:]  # rows Q a_t - p_t


def _gradient(terms: _TakeTerms, weights, residual):
    """E's gradient at ``weights`` (zero on held frames), from the solved frames' residuals
    Q a_t - p_t (``_residuals``)."""
    problem, gram, h = terms.problem, terms.problem.gram, terms.history
    k = weights.shape[1]
    jacobian = jax.vmap(problem.jacobian)(weights[h:])  # (T - h, K, P) G_t
    data_grad = jnp.einsum("tkp,tp->tk", jacobian, residual)
    data_grad = jnp.concatenate([jnp.zeros((h, k), gram.dtype), data_grad])
    grad = data_grad + terms.alpha + _time_gradient(terms, weights)
    return jnp.where(terms.held[:, None], 0.0, grad)


def _newton_step(terms: _TakeTerms, weights, grad, blocks) -> Float[Array, "T K"]:
    """The projected Gauss-Newton step: the epsilon-active set (weights at a bound whose
    gradient pushes them out) held, the block-banded system (data blocks + time bands) solved
    on the free weights of the solved frames; zero on held weights and where not finite."""
    h, upper, dtype = terms.history, terms.upper, terms.dtype
    n, k = weights.shape
    bands = terms.bands
    data = jnp.concatenate([jnp.zeros((h, k, k), dtype), blocks])
    data = jnp.where(terms.held[:, None, None], 0.0, data)
    eps = jnp.minimum(1e-3 * upper, jnp.linalg.norm(weights - jnp.clip(weights - grad, 0.0, upper)))
    at_bound = ((weights <= eps) & (grad > 0)) | ((weights >= upper - eps) & (grad < 0))
    free = ~at_bound & terms.solved[:, None]
    eye = jnp.eye(k, dtype=dtype)
    band0 = data + bands[0][:, None, None] * eye
    ridge = 1e-6 * jnp.max(jnp.abs(jnp.diagonal(band0, axis1=1, axis2=2)))
    band0 = jnp.where(free[:, :, None] & free[:, None, :], band0, 0.0)
    band0 = band0 + jax.vmap(jnp.diag)(jnp.where(free, ridge, 1.0))
    band1 = jax.vmap(jnp.diag)(bands[1][: n - 1, None] * (free[1:] & free[:-1]))
    band2 = jax.vmap(jnp.diag)(bands[2][: n - 2, None] * (free[2:] & free[:-2]))
    rhs = -jnp.where(free, grad, 0.0)
    # the history is held (identity rows, zero right-hand side, no coupling to a free
    # weight): its step is 0, so only the solved frames enter the solve
    banded = dense_banded_solve if (n - h) * k <= DENSE_WINDOW else block_banded_solve
    step = banded(band0[h:], band1[h:], band2[h:], rhs[h:])
    step = jnp.concatenate([jnp.zeros((h, k), step.dtype), step])
    return jnp.where(free & jnp.isfinite(step), step, 0.0)


def _decreases(terms: _TakeTerms, weights, trials, a, residual):
    """(E(trial) - E(W), the trials' (a, residual)) for each of the (L, T, K) ``trials``:
    data terms in coefficient space (no cancellation against ||b - b0||^2), from W's
    coefficients ``a`` and residuals Q a_t - p_t, and the time terms exactly; each trial's
    coefficients, and its residuals as W's plus Q (a_trial - a) (the product the decrease
    needs anyway), so that the next iteration need not recompute them."""
    problem, gram, h = terms.problem, terms.problem.gram, terms.history
    coefficients = jax.vmap(jax.vmap(problem.coefficients))(trials[:, h:])
    change = coefficients - a
    change_gram = change @ gram
    data_change = jnp.sum(change * residual, axis=(1, 2)) + 0.5 * jnp.sum(
        change_gram * change, axis=(1, 2)
    )
    moved = trials - weights
    time_change = jax.vmap(lambda c: jnp.sum(c * _time_gradient(terms, weights)))(moved)
    time_change = time_change + jax.vmap(
        lambda c: _weighted_time_penalty(
            c, terms.smoothness, terms.velocity, terms.rows2, terms.rows1
        )  # fmt: skip
    )(moved)
    decrease = data_change + terms.alpha * moved.sum(axis=(1, 2)) + time_change
    return decrease, (coefficients, residual + change_gram)


def _line_search(terms: _TakeTerms, weights, step, a, residual, line_steps: int):
    """(weights, gain, (a, residual)): the projected trials W + 2^-j step
    (j < ``line_steps``), each clipped to the box, scored by E(trial) - E(W)
    (``_decreases``); the best one if it lowers E (gain its decrease), else W (gain 0)."""
    lengths = 0.5 ** jnp.arange(line_steps, dtype=terms.dtype)
    trials = jnp.clip(weights + lengths[:, None, None] * step, 0.0, terms.upper)  # (L, T, K)
    decrease, (coefficients, residuals) = _decreases(terms, weights, trials, a, residual)
    best = jnp.argmin(decrease)
    better = decrease[best] < 0
    fit = jnp.where(better, coefficients[best], a), jnp.where(better, residuals[best], residual)
    return jnp.where(better, trials[best], weights), jnp.where(better, -decrease[best], 0.0), fit


ARMIJO = 0.3
"""Sufficient decrease for ``TemporalNewton(stream_steps="newton_first")``'s full step: it is
taken when E(trial) - E(W) <= ``ARMIJO`` grad . (trial - W) (Armijo's rule). Below 1/2, so
that a Newton step on a quadratic E (which gains half of grad . step) passes; well above the
usual 1e-4, so that an overshooting full step which a shorter length would beat goes to the
line search (at 1e-4 the lagged stream took 3 % more iterations on ict-quartic)."""


def _newton_first(terms: _TakeTerms, weights, step, a, residual, grad, line_steps: int):
    """(weights, gain, (a, residual)): the full projected step W + step (clipped to the box)
    when it decreases E enough (``ARMIJO``), scored alone (one trial instead of
    ``line_steps``); otherwise ``_line_search`` over every length."""
    trial = jnp.clip(weights + step, 0.0, terms.upper)
    decrease, (coefficients, residuals) = _decreases(terms, weights, trial[None], a, residual)
    decrease = decrease[0]
    slope = jnp.sum(grad * (trial - weights))  # grad . (trial - W), < 0 for a descent step
    sufficient = (decrease < 0) & (decrease <= ARMIJO * slope)
    return jax.lax.cond(
        sufficient,
        lambda: (trial, -decrease, (coefficients[0], residuals[0])),
        lambda: _line_search(terms, weights, step, a, residual, line_steps),
    )


def _small_gain(gain, value, tol) -> Bool[Array, ""]:
    """The stopping test: the last iteration lowered E by at most ``tol`` relative to E."""
    return gain <= tol * jnp.abs(value)


def take_objective(
    problem: InverseProblem,
    weights: Float[ArrayLike, "T K"],
    offsets: Float[ArrayLike, "T N"],
    alpha: Any,
    smoothness: Any,
    velocity: Any = 0.0,
) -> Float[Array, ""]:
    """E(W) of a take (module docstring) in squared rig units, data terms from the Gram
    matrix; ``offsets`` (T, 3V) = b_t - b0 flattened."""
    dtype = problem.columns.dtype
    weights, offsets = jnp.asarray(weights, dtype), jnp.asarray(offsets, dtype)
    projections = offsets @ problem.columns.T
    data = jax.vmap(lambda w, p, o: problem.objective(w, p, o @ o, alpha))(
        weights, projections, offsets
    )
    return data.sum() + time_penalty(weights, smoothness, velocity)


def window_owner(n_frames: int, window: int | None) -> Int[np.ndarray, " T"]:
    """(T,) the window (index into ``window_starts``) that weighs each frame most; zeros when
    the take is solved whole."""
    if window is None or n_frames <= window:
        return np.zeros(n_frames, np.int64)
    return _window_owner(window_starts(n_frames, window), window, n_frames)


__all__ = [
    "DEFAULT_SMOOTHNESS_CM2",
    "AbstractTemporalMethod",
    "TemporalNewton",
    "block_banded_solve",
    "block_tridiagonal_solve",
    "difference_bands",
    "stitch_windows",
    "take_objective",
    "time_penalty",
    "time_terms_per_frame",
    "weighted_difference_bands",
    "window_owner",
    "window_starts",
]
