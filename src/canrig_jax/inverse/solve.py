"""One entry point for every inverse-rig method: ``solve(problem, target, method) -> Solution``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import ArrayLike, Float

from ..rig.blendshape import BlendshapeRig, _check_finite
from .coordinate_descent import ORDERS, QuarticCD, check_order, objective
from .jaxopt_solver import JaxoptLBFGSB
from .lmmm import LMMM
from .problem import InverseProblem, prepare
from .solution import Solution

L1_METHODS = (QuarticCD, LMMM, JaxoptLBFGSB)
"""Methods minimising the L1-penalised objective; the reported objective includes alpha 1^T w
for them and is the plain data term for the others."""


def solve(
    problem: InverseProblem | BlendshapeRig,
    target: Float[ArrayLike, "V 3"],
    method,
    *,
    order: str = "decreasing",
    init: Float[ArrayLike, " K"] | None = None,
    key: jax.Array | None = None,
) -> Solution:
    """Recover rig weights from a target mesh (units of the rig) with ``method``.

    Args:
        problem: ``prepare(rig)`` (prepare once and reuse; a rig is prepared on each call).
        target: (V, 3) mesh to match.
        method: a solver object (``QuarticCD``, ``LinearCD``, ``Seol``, ``Joshi``,
            ``Cetinaslan``).
        order: coordinate order for coordinate descent (see ``ORDERS``).
        init: (K,) initial weights for coordinate descent (default zeros, as the paper).
        key: PRNG key for ``order="random"``.

    Batch a take with ``jax.vmap(lambda b: solve(problem, b, method))(targets)``. The
    returned objective is 1/2 ||f(w) - b||^2 (+ alpha 1^T w for ``L1_METHODS``) under the
    full rig, whatever rig the method assumed.
    """
    if isinstance(problem, BlendshapeRig):
        problem = prepare(problem)
    if jnp.shape(target) != (problem.n_vertices, 3):
        raise ValueError(
            f"target: expected shape ({problem.n_vertices}, 3) to match the rig, "
            f"got {jnp.shape(target)}"
        )
    _check_finite("target", target)
    k = problem.n_blendshapes
    if init is None:
        init = jnp.zeros(k, problem.basis.dtype)
    elif jnp.shape(init) != (k,):
        raise ValueError(f"init: expected shape ({k},), got {jnp.shape(init)}")
    else:
        _check_finite("init", init)
        init = jnp.clip(jnp.asarray(init, problem.basis.dtype), 0.0, getattr(method, "upper", 1.0))
    check_order(order)
    offset = (jnp.asarray(target, problem.basis.dtype) - problem.neutral).reshape(-1)
    weights, history = method(problem, offset, init, order, key)
    l1 = method.alpha if isinstance(method, L1_METHODS) else 0.0
    value = objective(problem, weights, offset, l1)
    history = value[None] if history is None else history
    finite = jnp.all(jnp.isfinite(weights))
    result = optx.RESULTS.where(finite, optx.RESULTS.successful, optx.RESULTS.nonlinear_divergence)
    return Solution(weights=weights, objective=value, history=history, result=result)


def solve_sequence(
    problem: InverseProblem,
    targets: Float[ArrayLike, "T V 3"],
    method,
    *,
    order: str = "decreasing",
    warm_start: bool = False,
) -> Solution:
    """Solve a whole take. Frames are independent and ``vmap``ped unless ``warm_start``, in
    which case each frame starts from the previous frame's weights (a ``scan``). Warm starts
    can keep mutually exclusive shapes active across frames, as Racković et al. warn."""
    targets = jnp.asarray(targets)
    if targets.ndim != 3:
        raise ValueError(f"targets: expected shape (T, V, 3), got {targets.shape}")
    if not warm_start:
        return jax.jit(jax.vmap(lambda b: solve(problem, b, method, order=order)))(targets)

    def step(previous, target):
        solution = solve(problem, target, method, order=order, init=previous)
        return solution.weights, solution

    init = jnp.zeros(problem.n_blendshapes, problem.basis.dtype)
    _, solutions = jax.jit(lambda t: jax.lax.scan(step, init, t))(targets)
    return solutions


__all__ = ["ORDERS", "solve", "solve_sequence"]
