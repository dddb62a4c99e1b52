"""Shared input checks for public entry points: plain Python, run before any jit work.

Each raises a ``ValueError`` naming the argument. Checks on values skip traced arrays (the
value is unknown at trace time); validate concrete inputs at the public boundary.
"""

from typing import Any

import numpy as np
from jax.core import Tracer
from jaxtyping import Float32, Shaped


def is_concrete(x: Any) -> bool:
    """True unless ``x`` is a JAX tracer (its values are known)."""
    return not isinstance(x, Tracer)


def check_finite(name: str, x: Any) -> None:
    """ValueError naming ``name`` when the concrete array ``x`` holds NaN or inf."""
    if is_concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")


def check_real(name: str, x: Any) -> None:
    """TypeError naming ``name`` unless ``x`` (an array, traced or not, or array-like) holds
    real numbers: integers, floats or booleans; not complex numbers, strings or objects."""
    dtype = x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype
    if np.issubdtype(dtype, np.complexfloating) or not (
        np.issubdtype(dtype, np.number) or np.issubdtype(dtype, np.bool_)
    ):
        raise TypeError(f"{name}: expected real numbers, got dtype {dtype}")


def native(x: Shaped[np.ndarray, "*shape"]) -> Shaped[np.ndarray, "*shape"]:
    """A NumPy array in the machine's byte order, contiguous (JAX rejects big-endian arrays
    and stages strided ones through a compiled copy)."""
    x = np.ascontiguousarray(x)
    if x.dtype.byteorder not in ("=", "|"):
        x = x.astype(x.dtype.newbyteorder("="))
    return x


def check_points(
    name: str, value: Any, n_vertices: int, *, frames: bool = False
) -> Float32[np.ndarray, "*frames V 3"]:
    """``value`` as float32 points of the mesh, (V, 3) or with ``frames`` (F >= 1, V, 3):
    real, finite, the mesh's vertex count; else TypeError/ValueError naming ``name``."""
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating) and not np.issubdtype(array.dtype, np.integer):
        raise TypeError(f"{name}: expected real numbers, got dtype {array.dtype}")
    expected = "(F, V, 3) with F >= 1 frames" if frames else "(V, 3)"
    if array.shape[-2:] != (n_vertices, 3) or array.ndim != (3 if frames else 2) or not len(array):
        raise ValueError(
            f"{name}: expected shape {expected}, V = {n_vertices} (the mesh's vertex count), "
            f"got {array.shape}"
        )
    array = array.astype(np.float32)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return array


__all__ = ["check_finite", "check_points", "check_real", "is_concrete", "native"]
