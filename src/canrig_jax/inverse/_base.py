"""The one interface every inverse-rig method implements.

A method is a small, immutable ``eqx.Module``: its hyper-parameters are fields, and
``inverse.solve`` calls it with the prepared problem, the target's offset from the neutral,
the (clipped) initial weights and a PRNG key. Concrete methods are final (never subclassed);
families that share code (coordinate descent) have their own abstract base.
"""

import abc
from typing import Any, NamedTuple

import equinox as eqx
import numpy as np
import optimistix as optx
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from .._checks import is_concrete
from ._problem import InverseProblem


class Iterate(NamedTuple):
    """What a method returns to ``solve``.

    Attributes:
        weights: (K,) the method's solution.
        history: (T,) objective after each step of the method (pass, iteration); T = 1 for a
            closed form.
        steps: number of passes / iterations actually taken.
        converged: True only when the method's stated stopping test held (its tolerance was
            met); False when it stopped at its cap or for any other reason first.
        result: optional ``optimistix.RESULTS`` naming why the method stopped, for methods
            with more than one way to stop short of the tolerance (L-BFGS-B's failed line
            search); None: ``solve`` derives it from ``converged``.
    """

    weights: Float[Array, " K"]
    history: Float[Array, " T"]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]
    result: optx.RESULTS | None = None


class AbstractInverseMethod(eqx.Module):
    """An inverse-rig method: weights in [0, ``upper``]^K from a target mesh.

    Attributes:
        alpha: the method's regularisation weight (>= 0).
        upper: upper bound of the box the weights live in (``jnp.inf`` for none).
        penalises_l1: class constant: True when the method minimises the L1-penalised
            objective 1/2 ||f(w) - b||^2 + alpha 1^T w, so that ``Solution.objective``
            includes alpha 1^T w; False for methods whose alpha means something else.
    """

    alpha: AbstractVar[float]
    upper: AbstractVar[float]
    penalises_l1: AbstractClassVar[bool]

    @abc.abstractmethod
    def __call__(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
    ) -> Iterate:
        """Solve for one frame; ``offset`` = (b - b0).ravel() in rig units. jit/vmap-safe."""

    def check(self, problem: InverseProblem) -> None:
        """Validate the method against ``problem`` in plain Python, before anything is
        compiled (``solve``, ``solve_sequence`` and ``Stream`` call it): per-weight settings
        of the wrong length, pairs past the rig's weights. Raises a ValueError naming the
        field; the default checks nothing."""

    def initial_carry(self, problem: InverseProblem) -> Any:
        """What ``Stream`` hands from one frame's solve to the next besides the weights
        (``step``), before the first frame; None for methods that reuse nothing else."""
        return None

    def step(
        self,
        problem: InverseProblem,
        offset: Float[Array, " N"],
        init: Float[Array, " K"],
        key: PRNGKeyArray,
        carry: Any,
    ) -> tuple[Iterate, Any]:
        """One frame of a ``Stream``: ``__call__`` and the carry for the next frame (a pytree
        of fixed structure, e.g. a matrix computed at the solution that the next,
        warm-started, frame starts from)."""
        return self(problem, offset, init, key), carry


def check_alpha(alpha: Any) -> None:
    if not is_concrete(alpha):
        return
    if not alpha >= 0:
        raise ValueError(f"alpha: expected a non-negative, finite weight, got {alpha}")
    if alpha == float("inf"):
        raise ValueError(f"alpha: expected a finite weight, got {alpha}")


def check_upper(upper: Any, per_weight: bool = False) -> None:
    """A positive upper bound; with ``per_weight``, also a (K,) array of bounds >= 0 (a bound
    of 0 holds its weight at 0)."""
    if not is_concrete(upper):
        return
    if per_weight and np.ndim(upper) == 1:
        bounds = np.asarray(upper)
        if bounds.size == 0 or np.any(np.isnan(bounds)) or np.any(bounds < 0):
            raise ValueError(f"upper: expected per-weight upper bounds >= 0, got {bounds}")
        return
    if np.ndim(upper) != 0:
        want = "a number or a (K,) array" if per_weight else "a number"
        raise ValueError(f"upper: expected {want}, got shape {np.shape(upper)}")
    if not upper > 0:
        raise ValueError(f"upper: expected a positive upper bound, got {upper}")


def check_tol(tol: Any) -> None:
    """A relative tolerance in [0, 1) (unchecked when traced)."""
    if is_concrete(tol) and not 0 <= tol < 1:
        raise ValueError(f"tol: expected a relative tolerance in [0, 1), got {tol}")


def check_count(name: str, value: Any) -> None:
    if isinstance(value, bool) or not (isinstance(value, int) and value >= 1):
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
