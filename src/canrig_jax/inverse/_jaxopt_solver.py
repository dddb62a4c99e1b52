"""A joint bounded solver through jaxopt on the same objective and the same ``evaluate``.

jaxopt is an optional dependency (``pip install canrig_jax[jaxopt]``), imported when a
``JaxoptLBFGSB`` is made."""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jax.custom_batching import sequential_vmap
from jaxtyping import Array, Float, PRNGKeyArray

from ..rig import evaluate
from ._base import AbstractInverseMethod, Iterate, check_alpha, check_count, check_upper
from ._problem import InverseProblem


class JaxoptLBFGSB(AbstractInverseMethod):
    """``jaxopt.LBFGSB`` on 1/2 ||f(w) - b||^2 + alpha 1^T w over [0, upper]^K (the L1 term is
    smooth on the box), from the initial weights (zero by default).

    Its stopping test is jaxopt's: the projected gradient step ||clip(w - grad E, 0, upper) -
    w||_inf <= ``tol`` (absolute, in objective units per unit weight). ``Solution.result``
    says how the run ended: ``successful`` when that test held; ``max_steps_reached`` when
    it ran all ``maxiter`` iterations without it; ``stagnation`` when the line search found
    no acceptable step first (the run stops there: in float32 this is how most frames of a
    real take end, near but not at the tolerance); ``nonlinear_divergence`` when the run
    ended with a non-finite value (a failed line search can divide by a zero curvature
    pair), in which case the weights are the start, never NaN.

    Attributes:
        alpha: L1 weight (>= 0).
        maxiter: cap on the L-BFGS-B iterations.
        tol: projected-gradient tolerance (absolute, see above).
        objective: ``"evaluate"`` differentiates ``rig.evaluate`` itself (3V-sized work per
            call); ``"gram"`` the same function in coefficient space (P x P work, about 40x
            cheaper on ict-quartic). Both give the same minimiser.
        upper: box upper bound.
    """

    alpha: float = 0.0
    maxiter: int = eqx.field(static=True, default=200)
    tol: float = 1e-4
    objective: str = eqx.field(static=True, default="gram")
    upper: float = 1.0
    penalises_l1: ClassVar[bool] = True

    def __check_init__(self):
        _jaxopt()
        check_alpha(self.alpha)
        check_count("maxiter", self.maxiter)
        check_upper(self.upper)
        if self.objective not in ("gram", "evaluate"):
            raise ValueError(f"objective: expected 'gram' or 'evaluate', got {self.objective!r}")

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        projection, offset_sq = problem.projection(offset), offset @ offset
        params, steps, error, failed_linesearch = _run_lbfgsb(self, problem, offset, init)
        fun = _objective(self, problem, offset)
        value = problem.objective(params, projection, offset_sq, self.alpha)
        finite = jnp.all(jnp.isfinite(params)) & jnp.isfinite(value) & jnp.isfinite(error)
        weights = jnp.where(finite, jnp.clip(params, 0.0, self.upper), init)  # box round-off
        history = jnp.where(finite, value, fun(init))[None]
        converged = finite & (error <= self.tol)
        results = optx.RESULTS
        short = results.where(failed_linesearch, results.stagnation, results.max_steps_reached)
        result = results.where(
            finite,
            results.where(converged, results.successful, short),
            results.nonlinear_divergence,
        )
        return Iterate(weights, history, steps, converged, result)


def _jaxopt():
    """The jaxopt module; ImportError naming the extra that installs it when it is missing."""
    try:
        import jaxopt
    except ImportError as error:
        raise ImportError(
            "JaxoptLBFGSB needs jaxopt, an optional dependency: pip install canrig_jax[jaxopt]"
        ) from error
    return jaxopt


def _objective(method: JaxoptLBFGSB, problem: InverseProblem, offset):
    """The function L-BFGS-B minimises over the weights (``method.objective``)."""
    projection, offset_sq = problem.projection(offset), offset @ offset
    target = problem.neutral + offset.reshape(-1, 3)

    def fun(weights):
        if method.objective == "gram":
            return problem.objective(weights, projection, offset_sq, method.alpha)
        residual = evaluate(problem.rig, weights) - target
        return 0.5 * jnp.sum(residual**2) + method.alpha * jnp.sum(weights)

    return fun


@sequential_vmap
def _run_lbfgsb(method: JaxoptLBFGSB, problem: InverseProblem, offset, init):
    """(weights, iterations, projected-gradient error, line search failed) of one frame.
    jaxopt's L-BFGS-B inverts its small compact-representation matrices with LAPACK: under
    ``vmap`` the frames run one after another (``sequential_vmap``), so that no LAPACK call
    ever holds a batch (see ``canrig_jax._linalg``)."""
    solver = _jaxopt().LBFGSB(
        fun=_objective(method, problem, offset),
        maxiter=method.maxiter,
        tol=method.tol,
        stop_if_linesearch_fails=True,
    )
    bounds = (jnp.zeros_like(init), jnp.full_like(init, method.upper))
    params, state = solver.run(init, bounds=bounds)
    return params, state.iter_num, state.error, state.failed_linesearch
