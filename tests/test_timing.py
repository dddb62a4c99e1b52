"""canrig_jax.median_ms: one warm-up call not counted, then the median of the timed calls."""

from __future__ import annotations

import pytest

from canrig_jax import median_ms


def test_median_ms_warms_up_once_then_times_each_repeat():
    calls = []
    median_ms(lambda: calls.append(1), repeats=5)
    assert len(calls) == 6  # the warm-up (compilation) call plus five timed ones


def test_median_ms_refuses_no_repeats():
    with pytest.raises(ValueError, match="^repeats:"):
        median_ms(lambda: None, repeats=0)
