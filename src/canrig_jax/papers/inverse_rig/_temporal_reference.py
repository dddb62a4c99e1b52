"""A NumPy/SciPy re-implementation of Racković et al. 2024's temporal solver ("holistic"
coordinate descent), written from the paper's description for comparison with
``TemporalNewton``.

The take is cut into intervals of ``interval`` frames (10 in the paper), solved in order.
Within an interval, with weights C (K x T) and the second-difference matrix D ((T-2) x T),
the objective is

    J(C) = (1/n) ||F(C) - B||^2 + (lambda1/m) 1^T C 1 + lambda2 ||C D^T||^2,   C in [0, 1],

n = 3V mesh coordinates, m = K controllers. After the first interval, the last two frames of
the previous interval are known and enter the second differences of the interval's first two
frames. Coordinate descent visits the controllers (decreasing blendshape norm); for controller
i the rig is affine in its row c_i, F(C)_t = psi_t + c_it phi_t, with psi_t the mesh at
c_it = 0 (the whole rig evaluated, dense, float64) and phi_t the sum of the columns that c_i
multiplies; so the controller's subproblem is the T-variable box QP

    min_x  x^T (diag(Phi) + lambda2 D^T D) x + x^T (2 Theta + lambda1/m + past terms),
    Phi_t = ||phi_t||^2 / n,  Theta_t = phi_t^T (psi_t - b_t) / n,   0 <= x <= 1,

solved with ``scipy.optimize.minimize(method="L-BFGS-B")`` from the current row (here with its
exact gradient). An interval starts from C = 0 and makes at least ``passes_min`` + 1 and at
most ``passes_max`` passes; after ``passes_min`` it stops (keeping the previous pass's C)
as soon as a pass does not lower J.

Mapping to ``TemporalNewton``'s E(W) = sum_t [1/2 ||f(w_t) - b_t||^2 + alpha 1^T w_t]
+ smoothness/2 ||D W||^2: (n/2) J = E with

    alpha = n lambda1 / (2 m),    smoothness = n lambda2
    (lambda1 = 2 m alpha / n,     lambda2 = smoothness / n;  ``holistic_lambdas``).

Differences from the whole-take E: intervals are solved one after another (a frame never
sees the frames after its interval), and the remainder of a take that is not a multiple of
``interval`` is solved as a shorter last interval (the published driver drops it).
"""

import numpy as np
from jaxtyping import ArrayLike, Float, Float64
from scipy.optimize import minimize

from ...rig import BlendshapeRig
from ._reference import NumpyDenseRig


def holistic_lambdas(
    alpha: float, smoothness: float, n_coordinates: int, n_blendshapes: int
) -> tuple[float, float]:
    """(lambda1, lambda2) of the holistic objective J for ``TemporalNewton``'s (alpha,
    smoothness): lambda1 = 2 m alpha / n, lambda2 = smoothness / n (n = 3V, m = K)."""
    if not (alpha >= 0 and smoothness >= 0):
        raise ValueError(f"alpha, smoothness: expected >= 0, got {alpha}, {smoothness}")
    return 2.0 * n_blendshapes * alpha / n_coordinates, smoothness / n_coordinates


class _DenseColumns:
    """The rig as one dense (P, 3V) float64 matrix M and its coefficient map, for evaluating
    many frames in one product (the authors' ``quartic_rig`` on a weight matrix)."""

    def __init__(self, rig: NumpyDenseRig):
        self.neutral = rig.neutral
        self.tables = [indices for indices, _ in rig.tables]
        self.matrix = np.concatenate([rig.deltas, *(dense for _, dense in rig.tables)])
        k = rig.n_blendshapes
        # for each controller: the columns its weight multiplies and the other members
        self.support: list[list[tuple[int, np.ndarray]]] = [
            [(i, np.zeros(0, int))] for i in range(k)
        ]
        column = k
        for indices in self.tables:
            for row in indices:
                for i in row:
                    self.support[i].append((column, row[row != i]))
                column += 1

    def coefficients(self, weights: np.ndarray) -> np.ndarray:
        """(T, P) a(w) of weights (T, K)."""
        return np.concatenate(
            [weights, *(np.prod(weights[:, idx], axis=2) for idx in self.tables)], axis=1
        )

    def meshes(self, weights: np.ndarray) -> np.ndarray:
        """(T, 3V) rig meshes minus the neutral."""
        return self.coefficients(weights) @ self.matrix

    def direction(self, weights: np.ndarray, i: int) -> np.ndarray:
        """(T, 3V) phi_t: d mesh / d w_i (independent of w_i)."""
        columns = [c for c, _ in self.support[i]]
        slopes = np.stack(
            [np.prod(weights[:, others], axis=1) for _, others in self.support[i]], axis=1
        )
        return slopes @ self.matrix[columns]


def _second_difference_matrix(n: int) -> np.ndarray:
    return np.diff(np.eye(n), n=2, axis=0) if n >= 3 else np.zeros((0, n))


def numpy_holistic_cd(
    rig: BlendshapeRig | NumpyDenseRig,
    targets: Float[ArrayLike, "T V 3"],
    lambda1: float,
    lambda2: float,
    *,
    interval: int = 10,
    passes_max: int = 10,
    passes_min: int = 5,
) -> Float64[np.ndarray, "T K"]:
    """Racković et al. 2024's holistic coordinate descent over ``interval``-frame intervals
    (module docstring); NumPy float64 and SciPy L-BFGS-B, CPU, one interval after another.

    Args:
        rig: the rig (or its ``NumpyDenseRig``).
        targets: (T, V, 3) meshes, rig units.
        lambda1, lambda2: the paper's sparsity and smoothness weights (``holistic_lambdas``
            maps ``TemporalNewton``'s alpha and smoothness to them).
        interval: frames per interval (>= 3).
        passes_max, passes_min: coordinate-descent passes per interval.

    Returns:
        (T, K) float64 weights in [0, 1].
    """
    if not isinstance(rig, NumpyDenseRig):
        rig = NumpyDenseRig(rig)
    targets = np.asarray(targets, np.float64)
    if targets.ndim != 3 or targets.shape[1:] != (rig.n_vertices, 3):
        raise ValueError(f"targets: expected (T, {rig.n_vertices}, 3), got {targets.shape}")
    if not (lambda1 >= 0 and lambda2 >= 0):
        raise ValueError(f"lambda1, lambda2: expected >= 0, got {lambda1}, {lambda2}")
    if not (isinstance(interval, int) and interval >= 3):
        raise ValueError(f"interval: expected an integer >= 3, got {interval!r}")
    if not (1 <= passes_min + 1 <= passes_max):
        raise ValueError(
            f"passes_min, passes_max: expected 0 <= min < max, got {passes_min}, {passes_max}"
        )
    dense = _DenseColumns(rig)
    k, n = rig.n_blendshapes, targets.shape[1] * 3
    order = np.argsort(-np.linalg.norm(rig.deltas, axis=1), kind="stable")
    offsets = targets.reshape(len(targets), -1) - rig.neutral
    solved: list[np.ndarray] = []
    for start in range(0, len(targets), interval):
        past = np.concatenate(solved[-1:] or [np.zeros((0, k))])[-2:]  # (<= 2, K)
        block = _solve_interval(
            dense, offsets[start : start + interval], past, order, lambda1 / k, lambda2, n,
            passes_max, passes_min,
        )  # fmt: skip
        solved.append(block)
    return np.concatenate(solved)


def _solve_interval(dense, offsets, past, order, sparsity, lambda2, n, passes_max, passes_min):
    frames, k = offsets.shape[0], past.shape[1]
    known = past.shape[0]
    # second differences of [past; x]: D_ext = [A | B], ||A p + B x||^2 per controller
    d_ext = _second_difference_matrix(known + frames)
    d_past, d_new = d_ext[:, :known], d_ext[:, known:]
    curvature = lambda2 * d_new.T @ d_new  # F (or F tilde)
    past_linear = 2.0 * lambda2 * (d_new.T @ (d_past @ past))  # (T, K)
    weights = np.zeros((frames, k))

    def cost(w):
        residual = dense.meshes(w) - offsets
        smooth = d_new @ w + d_past @ past
        return (residual**2).sum() / n + sparsity * w.sum() + lambda2 * (smooth**2).sum()

    previous = np.inf
    for sweep in range(passes_max):
        kept = weights.copy()
        for i in order.tolist():
            rest = weights.copy()
            rest[:, i] = 0.0
            psi = dense.meshes(rest) - offsets  # (T, 3V): the whole rig at c_i = 0
            phi = dense.direction(weights, i)
            hessian = np.diag((phi**2).sum(axis=1) / n) + curvature
            linear = 2.0 * (phi * psi).sum(axis=1) / n + sparsity + past_linear[:, i]
            result = minimize(
                lambda x, h=hessian, g=linear: (x @ h @ x + x @ g, 2.0 * h @ x + g),
                weights[:, i],
                jac=True,
                method="L-BFGS-B",
                bounds=[(0.0, 1.0)] * frames,
            )
            weights[:, i] = np.clip(result.x, 0.0, 1.0)
        value = cost(weights)
        if sweep >= passes_min and value >= previous:
            return kept
        previous = value
    return weights
