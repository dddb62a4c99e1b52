"""The uniform result of every inverse-rig solver."""

from __future__ import annotations

import equinox as eqx
import optimistix as optx
from jaxtyping import Array, Float


class Solution(eqx.Module):
    """Result of ``inverse.solve``.

    Attributes:
        weights: (K,) recovered weights.
        objective: 1/2 ||f(w) - b||^2 + alpha 1^T w under the full rig (cm^2), with the
            method's alpha (0 for methods without one).
        history: (T,) objective after each pass (T = 1 for closed-form methods); with
            ``trace=True`` on coordinate descent, after every coordinate update.
        result: ``optimistix.RESULTS`` code.
    """

    weights: Float[Array, " K"]
    objective: Float[Array, ""]
    history: Float[Array, " T"]
    result: optx.RESULTS
