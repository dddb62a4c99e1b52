"""The bad-input suite: one parametrised table of ``Case``s per public entry point.

A case either raises (``raises``: the exception type, ``names``: text its message must
contain, the argument or the file) before any JIT compilation, or is handled (``check``
receives the result and asserts it is the correct one). No handled case may return NaN.
A new public function gets its bad inputs as one more table in its package's file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np
import pytest

_COMPILES = [0]


STAGING = ("jit(stage)",)
"""Compilations that only move an array to the device (``jnp.asarray`` of a new shape)."""


def _count_compiles(event: str, duration: float, fun_name: str = "", **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration" and fun_name not in STAGING:
        _COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compiles)


@dataclasses.dataclass(frozen=True)
class Case:
    """One bad input of one entry point.

    ``call(ctx)`` runs the entry point on the bad input (``ctx``: the file's fixtures).
    ``raises``/``names``: the exception expected and text its message must contain.
    ``check(result, ctx)``: for a handled input, asserts the result is the correct one.
    """

    id: str
    call: Callable
    raises: type[BaseException] | tuple | None = None
    names: str = ""
    check: Callable | None = None
    compiles: bool = False
    """The error can only be found after building a model (an old checkpoint without a hash
    is checked against the model its header describes): compilations before it allowed."""

    @property
    def param(self):
        return pytest.param(self, id=self.id)


def raises(id, call, exception, names, compiles=False) -> pytest.param:
    return Case(id, call, exception, names, compiles=compiles).param


def handled(id, call, check) -> pytest.param:
    return Case(id, call, None, "", check).param


def _float_leaves(tree):
    leaves = jax.tree_util.tree_leaves(tree)
    out = []
    for leaf in leaves:
        if isinstance(leaf, np.ndarray | jax.Array) and np.issubdtype(leaf.dtype, np.inexact):
            out.append(np.asarray(leaf))
        elif isinstance(leaf, float):
            out.append(np.asarray(leaf))
    return out


def run_case(case: Case, ctx) -> None:
    """Run one case: the expected error, named, with no compilation before it; or a correct
    result without NaN."""
    if case.raises is not None:
        before = _COMPILES[0]
        with pytest.raises(case.raises) as info:
            case.call(ctx)
        message = str(info.value)
        assert case.names in message, f"message does not name {case.names!r}: {message}"
        compiled = _COMPILES[0] - before
        assert case.compiles or compiled == 0, f"{compiled} JIT compilation(s) before the error"
        return
    result = case.call(ctx)
    for leaf in _float_leaves(result):
        assert not np.any(np.isnan(leaf)), "a handled bad input returned NaN"
    case.check(result, ctx)
