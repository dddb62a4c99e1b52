"""A NumPy reference of Racković et al. 2023, Algorithm 1, written as the authors publish it.

Coordinate descent on

    E(w) = 1/2 ||f(w) - b||^2 + alpha 1^T w,    0 <= w <= 1,    w initialised to 0,

where f is the full rig (neutral + blendshapes + every corrective order, eq. (5)). For each
coordinate i of the sequence, the rig is evaluated twice, in full, on dense float64 arrays:

    psi = f(w | w_i = 0) - b,   phi = f(w | w_i = 1) - f(w | w_i = 0),
    w_i <- clip((-phi^T psi - alpha) / ||phi||^2, 0, 1)     (w_i <- 0 when ||phi|| = 0).

No residual bookkeeping, no Gram matrix: two 3V x P matrix-vector products per coordinate
(P = K + number of correctives). This is the baseline the library's coefficient-space
``inverse.QuarticCD`` is timed against; ``measure_reference`` times both in one process
(``benchmarks/bench_inverse.py`` and ``experiments/inverse_rig.py``).
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, Float64, Int

from ...inverse import (
    AbstractInverseMethod,
    InverseProblem,
    QuarticCD,
    Stream,
    prepare,
    solve_sequence,
)
from ...rig import BlendshapeRig


class NumpyDenseRig:
    """Eq. (5) in NumPy float64 on dense arrays (built once, outside any timed loop).

    Attributes:
        neutral: (3V,) rest mesh, flattened.
        deltas: (K, 3V) blendshape offsets.
        tables: one ((C, n) int indices, (C, 3V) dense offsets) pair per corrective order.
    """

    def __init__(self, rig: BlendshapeRig):
        v, k = rig.n_vertices, rig.n_blendshapes
        self.n_vertices = v
        self.neutral = np.asarray(rig.neutral, np.float64).reshape(-1)
        self.deltas = np.asarray(rig.deltas, np.float64).reshape(k, -1)
        self.tables = [
            (
                np.asarray(c.indices, np.int64),
                c.to_dense(v).reshape(c.indices.shape[0], -1).astype(np.float64),
            )
            for c in rig.correctives
            if c.indices.shape[0]
        ]

    @property
    def n_blendshapes(self) -> int:
        return self.deltas.shape[0]

    @property
    def n_columns(self) -> int:
        """P = K + number of correctives (all orders)."""
        return self.n_blendshapes + sum(indices.shape[0] for indices, _ in self.tables)

    def __call__(self, weights: Float[ArrayLike, " K"]) -> Float64[np.ndarray, " N"]:
        """(3V,) mesh at ``weights`` (K,): the whole rig, every term."""
        weights = np.asarray(weights)
        mesh = self.neutral + weights @ self.deltas
        for indices, dense in self.tables:
            mesh = mesh + np.prod(weights[indices], axis=1) @ dense
        return mesh


def numpy_quartic_cd(
    rig: BlendshapeRig | NumpyDenseRig,
    target: Float[ArrayLike, "V 3"],
    alpha: float,
    passes: int,
    order: Int[ArrayLike, " K"] | Int[ArrayLike, "P K"],
) -> Float64[np.ndarray, " K"]:
    """Algorithm 1 of Racković et al. 2023 with the full rig re-evaluated per coordinate.

    Args:
        rig: the rig, or a ``NumpyDenseRig`` of it (pass one to keep conversion untimed).
        target: (V, 3) mesh b, rig units.
        alpha: L1 weight (>= 0).
        passes: number of sweeps over the coordinates.
        order: coordinate sequence, (K,) for the same order in every pass (e.g.
            ``decreasing_norm_order``) or (>= passes, K), one row per pass.

    Returns:
        (K,) float64 weights in [0, 1].
    """
    if not isinstance(rig, NumpyDenseRig):
        rig = NumpyDenseRig(rig)
    target = np.asarray(target, np.float64)
    if target.shape != (rig.n_vertices, 3):
        raise ValueError(f"target: expected shape ({rig.n_vertices}, 3), got {target.shape}")
    if not alpha >= 0:
        raise ValueError(f"alpha: expected a non-negative L1 weight, got {alpha}")
    if not (isinstance(passes, int) and passes >= 1):
        raise ValueError(f"passes: expected an integer >= 1, got {passes}")
    order = np.asarray(order, np.int64)
    if order.ndim == 1:
        order = np.tile(order, (passes, 1))
    if order.ndim != 2 or order.shape[0] < passes:
        raise ValueError(f"order: expected (K,) or (>= {passes}, K) indices, got {order.shape}")
    k = rig.n_blendshapes
    if order.size and (order.min() < 0 or order.max() >= k):
        raise ValueError(f"order: indices must lie in [0, {k})")

    b = target.reshape(-1)
    weights = np.zeros(k)
    for sequence in order[:passes]:
        for i in sequence:
            low = weights.copy()
            low[i] = 0.0
            high = weights.copy()
            high[i] = 1.0
            rest = rig(low)
            psi = rest - b
            phi = rig(high) - rest
            curvature = phi @ phi
            if curvature == 0.0:
                weights[i] = 0.0
            else:
                weights[i] = np.clip((-(phi @ psi) - alpha) / curvature, 0.0, 1.0)
    return weights


def decreasing_norm_order(problem: InverseProblem) -> Int[np.ndarray, " K"]:
    """(K,) blendshapes by decreasing ||b_i|| (stable), the library's ``"decreasing"`` order."""
    return np.argsort(-np.asarray(problem.blendshape_norms), kind="stable")


def time_batched(
    problem: InverseProblem,
    targets: Float[ArrayLike, "T V 3"],
    method: AbstractInverseMethod,
    repeats: int = 3,
) -> tuple[float, Float[np.ndarray, "T K"]]:
    """(best-of-``repeats`` seconds per frame, (T, K) weights) of ``solve_sequence`` over the
    whole take (one vmapped call), compiled and warmed up first."""
    targets = jnp.asarray(targets, jnp.float32)
    weights = np.asarray(solve_sequence(problem, targets, method).weights)  # compile
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        solve_sequence(problem, targets, method).weights.block_until_ready()
        best = min(best, time.perf_counter() - start)
    return best / targets.shape[0], weights


def time_single_frames(
    problem: InverseProblem,
    targets: Float[ArrayLike, "T V 3"],
    method: AbstractInverseMethod,
    warm_start: bool = False,
    repeats: int = 3,
) -> tuple[float, Float[np.ndarray, "T K"]]:
    """(best-of-``repeats`` median seconds per frame, (T, K) weights) of ``Stream``: one
    compiled call per frame, each waited for (as a live capture would), host-side input
    checks included."""
    targets = np.asarray(targets, np.float32)
    Stream(problem, method)(targets[0]).weights.block_until_ready()  # compile
    best, weights = np.inf, None
    for _ in range(repeats):
        stream = Stream(problem, method, warm_start=warm_start)
        seconds, frames = [], []
        for target in targets:
            start = time.perf_counter()
            frames.append(stream(target).weights.block_until_ready())
            seconds.append(time.perf_counter() - start)
        if np.median(seconds) < best:
            best, weights = float(np.median(seconds)), np.stack(frames)
    assert weights is not None  # repeats >= 1
    return best, weights


def time_against_projection(
    problem: InverseProblem,
    targets: Float[ArrayLike, "T V 3"],
    method: AbstractInverseMethod,
    warm_start: bool = False,
    repeats: int = 3,
    lag: int | None = None,
) -> dict:
    """One frame per call (``Stream``) against the floor of any one-frame solve, timed in
    the same loop: before each frame, the exact projection M^T (b - b0) of that frame alone
    (one (P, 3V) matrix-vector product, compiled: it reads all of M once).

    Returns ``ms`` and ``projection_ms`` (best-of-``repeats`` medians over the frames),
    ``ratio`` (the median of the per-frame ratios, so that load shared by a frame and its
    projection cancels), ``steps`` (mean), ``converged`` (fraction of frames) and the (T, K)
    ``weights`` of the best repeat. With ``lag`` (``Stream(..., lag=lag)``) every call is
    timed, the first ``lag`` too (they solve the window as well), and the last frames come
    from ``flush`` (not timed)."""
    targets = np.asarray(targets, np.float32)
    project = jax.jit(lambda columns, target, neutral: columns @ (target - neutral).reshape(-1))
    args = (problem.columns, jnp.asarray(targets[0]), problem.neutral)
    project(*args).block_until_ready()  # compile
    options = {"warm_start": warm_start} if lag is None else {"lag": lag}
    warmup = Stream(problem, method, **options)
    first = warmup(targets[0])  # compiles
    jax.block_until_ready(warmup.state if first is None else first.weights)
    best: dict = {"ms": np.inf}
    for _ in range(repeats):
        stream = Stream(problem, method, **options)
        solve_s, project_s, solutions = [], [], []
        for target in targets:
            on_device = jnp.asarray(target)
            start = time.perf_counter()
            project(problem.columns, on_device, problem.neutral).block_until_ready()
            project_s.append(time.perf_counter() - start)
            start = time.perf_counter()
            solution = stream(target)
            if solution is None:
                jax.block_until_ready(stream.state)
            else:
                solution.weights.block_until_ready()
                solutions.append(solution)
            solve_s.append(time.perf_counter() - start)
        if lag is not None:
            solutions += stream.flush()
        if np.median(solve_s) * 1e3 < best["ms"]:
            best = {
                "ms": float(np.median(solve_s)) * 1e3,
                "projection_ms": float(np.median(project_s)) * 1e3,
                "ratio": float(np.median(np.asarray(solve_s) / np.asarray(project_s))),
                "steps": float(np.mean([int(s.stats["steps"]) for s in solutions])),
                "converged": float(np.mean([bool(s.stats["converged"]) for s in solutions])),
                "weights": np.stack([np.asarray(s.weights) for s in solutions]),
            }
    return best


def measure_reference(
    rig: BlendshapeRig,
    targets: Float[ArrayLike, "T V 3"],
    alpha: float = 0.5,
    passes: int = 5,
    n_reference_frames: int = 3,
    problem: InverseProblem | None = None,
) -> dict:
    """Seconds per frame of the NumPy reference and of ``inverse.QuarticCD`` with the same
    work (``passes`` passes, no stopping rule, no Newton step), in this process.

    The reference solves the first ``n_reference_frames`` frames one at a time (it is slow)
    and reports the fastest: its work is the same for every frame (2 x K x passes full-rig
    evaluations), so this is a best-of-n like the JAX timing. JAX solves all T frames at once
    (``solve_sequence``, best of 3 after compiling). Both use the decreasing-||b_i|| order.
    ``max_weight_difference`` is max |w_numpy - w_jax| over the reference frames; JAX works
    in float32, so ~1e-3 can occur where E is flat in a weight.
    """
    targets = np.asarray(targets)
    if targets.ndim != 3 or targets.shape[1:] != (rig.n_vertices, 3):
        raise ValueError(f"targets: expected shape (T, {rig.n_vertices}, 3), got {targets.shape}")
    if not 1 <= n_reference_frames <= targets.shape[0]:
        raise ValueError(
            f"n_reference_frames: expected 1..{targets.shape[0]}, got {n_reference_frames}"
        )
    problem = prepare(rig) if problem is None else problem
    order = decreasing_norm_order(problem)
    dense = NumpyDenseRig(rig)

    method = QuarticCD(alpha=alpha, passes=passes, tol=0.0, newton=False)
    jax_seconds, jax_weights = time_batched(problem, targets, method)

    numpy_weights, numpy_seconds = [], np.inf
    for target in targets[:n_reference_frames]:
        start = time.perf_counter()
        numpy_weights.append(numpy_quartic_cd(dense, target, alpha, passes, order))
        numpy_seconds = min(numpy_seconds, time.perf_counter() - start)

    difference = np.abs(np.stack(numpy_weights) - jax_weights[:n_reference_frames])
    return {
        "numpy_seconds_per_frame": numpy_seconds,
        "jax_seconds_per_frame": jax_seconds,
        "speedup": numpy_seconds / jax_seconds,
        "max_weight_difference": float(difference.max()),
    }


def minimum(
    problem: InverseProblem,
    target: Float[ArrayLike, "V 3"],
    alpha: float,
    upper: float = 1.0,
    init: Float[ArrayLike, " K"] | None = None,
) -> Float64[np.ndarray, " K"]:
    """(K,) float64 minimiser of 1/2 ||f(w) - b||^2 + alpha 1^T w on [0, upper]^K by SciPy's
    L-BFGS-B (float64, tight tolerances), independently of the library's solvers: the
    objective in coefficient space from the problem's Gram matrix, its gradient written out
    by the product rule, dE/dw_i = sum_{columns c containing i} (Q a - p)_c prod_{j in c, j != i}
    w_j + alpha. Used as "the minimum of the same objective" in the convergence table."""
    from scipy.optimize import minimize

    gram = np.asarray(problem.gram, np.float64)
    rows = np.asarray(problem.columns, np.float64)
    offset = (np.asarray(target, np.float64) - np.asarray(problem.neutral, np.float64)).ravel()
    projection, offset_sq = rows @ offset, offset @ offset
    tables = [np.asarray(c) for c in problem.combinations]
    k = problem.n_blendshapes

    def coefficients(w):
        return np.concatenate([w, *(np.prod(w[t], axis=1) for t in tables)])

    def fun(w):
        a = coefficients(w)
        residual = gram @ a - projection
        value = 0.5 * (a @ gram @ a - 2 * a @ projection + offset_sq) + alpha * w.sum()
        grad = residual[:k] + alpha
        column = k
        for t in tables:
            r = residual[column : column + len(t)]
            for j in range(t.shape[1]):
                others = np.prod(np.delete(w[t], j, axis=1), axis=1)
                np.add.at(grad, t[:, j], r * others)
            column += len(t)
        return value, grad

    start = np.zeros(k) if init is None else np.clip(np.asarray(init, np.float64), 0, upper)
    result = minimize(
        fun,
        start,
        jac=True,
        method="L-BFGS-B",
        bounds=[(0.0, upper)] * k,
        options={"maxiter": 5000, "ftol": 1e-13, "gtol": 1e-8},
    )
    return result.x
