"""Shared input checks for public entry points: plain Python, run before any jit work.

Each raises a ``ValueError`` naming the argument. Checks on values skip traced arrays (the
value is unknown at trace time); validate concrete inputs at the public boundary.
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(x) -> bool:
    """True unless ``x`` is a JAX tracer (its values are known)."""
    return not isinstance(x, jax.core.Tracer)


def check_finite(name: str, x) -> None:
    """ValueError naming ``name`` when the concrete array ``x`` holds NaN or inf."""
    if is_concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")


__all__ = ["check_finite", "is_concrete"]
