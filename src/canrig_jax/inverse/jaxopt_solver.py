"""A joint bounded solver through jaxopt on the same objective and the same ``evaluate``."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jaxopt

from ..rig.blendshape import evaluate
from .problem import InverseProblem


class JaxoptLBFGSB(eqx.Module):
    """``jaxopt.LBFGSB`` on 1/2 ||f(w) - b||^2 + alpha 1^T w over [0, 1]^K (the L1 term is
    smooth on the box), from zero weights.

    Attributes:
        objective: ``"evaluate"`` differentiates ``rig.evaluate`` itself (3V-sized work per
            call); ``"gram"`` the same function in coefficient space (P x P work, about 40x
            cheaper on ict-quartic). Both give the same minimiser.
    """

    alpha: float = 0.0
    maxiter: int = eqx.field(static=True, default=200)
    tol: float = 1e-4
    objective: str = eqx.field(static=True, default="gram")

    def __check_init__(self):
        if not self.alpha >= 0:
            raise ValueError(f"alpha: expected a non-negative L1 weight, got {self.alpha}")
        if not (isinstance(self.maxiter, int) and self.maxiter >= 1):
            raise ValueError(f"maxiter: expected an integer >= 1, got {self.maxiter}")
        if self.objective not in ("gram", "evaluate"):
            raise ValueError(f"objective: expected 'gram' or 'evaluate', got {self.objective!r}")

    def __call__(self, problem: InverseProblem, offset, init, order=None, key=None):
        rig = problem.rig
        target = problem.neutral + offset.reshape(-1, 3)
        projection, offset_sq = problem.basis.T @ offset, offset @ offset

        def fun(weights):
            if self.objective == "gram":
                return problem.objective(weights, projection, offset_sq, self.alpha)
            residual = evaluate(rig, weights) - target
            return 0.5 * jnp.sum(residual**2) + self.alpha * jnp.sum(weights)

        solver = jaxopt.LBFGSB(fun=fun, maxiter=self.maxiter, tol=self.tol)
        bounds = (jnp.zeros_like(init), jnp.ones_like(init))
        params, state = solver.run(init, bounds=bounds)
        return params, None
