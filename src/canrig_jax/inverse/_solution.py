"""The uniform result of every inverse-rig solver."""

import equinox as eqx
import optimistix as optx
from jaxtyping import Array, Float, Shaped


class Solution(eqx.Module):
    """Result of ``inverse.solve``.

    Attributes:
        weights: (K,) recovered weights (finite whenever the target and init are).
        objective: 1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig (squared rig units),
            with the method's alpha for methods that minimise it (0 for the others).
        history: (T,) objective after each pass / iteration (T = 1 for closed forms); with
            ``trace=True`` on coordinate descent, after every coordinate update.
        result: ``optimistix.RESULTS``: ``successful`` only when the method's stated
            convergence test held at the returned weights; ``max_steps_reached`` when an
            iterative method hit its cap first; ``stagnation`` when ``JaxoptLBFGSB``'s line
            search failed first, or no step length of ``QuarticNewton`` lowered the
            objective while its Gauss-Newton model predicted a decrease above ``tol``;
            ``nonlinear_divergence`` when the method produced a
            non-finite value (the weights are then the start, never NaN). The tests:
            ``QuarticCD``, ``LinearCD``, ``QuarticNewton`` and ``LMMM`` stop when one pass /
            iteration lowers their objective by less than ``tol`` relative to its value
            (coordinate descent with ``tol=0`` has no test and runs all its passes, reported
            ``successful``); ``JaxoptLBFGSB`` when its projected gradient step
            ||clip(w - grad, 0, upper) - w||_inf <= ``tol`` (absolute); one-pass and closed
            forms (``Seol``, ``Joshi``, ``Cetinaslan``) are always ``successful``.
        stats: ``steps`` (passes / iterations taken) and ``converged`` (bool, ``result ==
            successful``).
    """

    weights: Float[Array, " K"]
    objective: Float[Array, ""]
    history: Float[Array, " T"]
    result: optx.RESULTS
    stats: dict[str, Shaped[Array, ""]]
