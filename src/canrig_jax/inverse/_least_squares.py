"""Closed-form baselines on the linear rig, clipped to the [0, 1] box."""

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._linalg import spd_solve
from ._base import AbstractInverseMethod, Iterate, check_alpha
from ._problem import InverseProblem


def _closed_form(problem, offset, weights) -> Iterate:
    residual = weights @ problem.columns[: problem.n_blendshapes] - offset
    history = (0.5 * residual @ residual)[None]
    return Iterate(weights, history, jnp.asarray(1), jnp.asarray(True))


class Joshi(AbstractInverseMethod):
    """Joshi et al. 2006: pseudoinverse least squares w = B^+ (b - b0), clipped to [0, 1]."""

    alpha: ClassVar[float] = 0.0
    upper: ClassVar[float] = 1.0
    penalises_l1: ClassVar[bool] = False

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        weights = jnp.clip(problem.pseudoinverse @ offset, 0.0, 1.0)
        return _closed_form(problem, offset, weights)


class Cetinaslan(AbstractInverseMethod):
    """Çetinaslan & Orvalho 2020: (B^T B + 2 alpha I) w = B^T (b - b0), clipped to [0, 1].

    Attributes:
        alpha: ridge weight (>= 0); not an L1 weight, so the reported objective is the data
            term alone.
    """

    alpha: float = 0.0
    upper: ClassVar[float] = 1.0
    penalises_l1: ClassVar[bool] = False

    def __check_init__(self):
        check_alpha(self.alpha)

    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        return _closed_form(problem, offset, ridge_weights(problem, offset, self.alpha))


def ridge_weights(
    problem: InverseProblem, offset: Float[Array, " N"], alpha: float | Float[Array, ""]
) -> Float[Array, " K"]:
    """(K,) clip((B^T B + 2 alpha I)^-1 B^T (b - b0), 0, 1); ``alpha`` may be traced.

    A K x K Cholesky solve (``canrig_jax._linalg``: one matrix per LAPACK call under ``vmap``);
    the linear Gram matrix is positive definite for any rig ``prepare`` accepts (no zero
    blendshape)."""
    k = problem.n_blendshapes
    system = problem.gram[:k, :k] + 2.0 * alpha * jnp.eye(k, dtype=problem.gram.dtype)
    weights = spd_solve(system, problem.columns[:k] @ offset)
    return jnp.clip(weights, 0.0, 1.0)
