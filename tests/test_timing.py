"""canrig_jax._timing.median_ms: one warm-up call not counted, then the timed calls' median."""

from __future__ import annotations

import time

import pytest

from canrig_jax._timing import call_times_ms, median_ms


def test_median_ms_warms_up_once_then_times_each_repeat():
    calls = []
    median_ms(lambda: calls.append(1), repeats=5)
    assert len(calls) == 6  # the warm-up (compilation) call plus five timed ones


def test_median_ms_refuses_no_repeats():
    with pytest.raises(ValueError, match="^repeats:"):
        median_ms(lambda: None, repeats=0)


def test_call_times_ms_lists_each_timed_call_and_median_ms_is_their_median():
    calls = []
    times = call_times_ms(lambda: calls.append(1), repeats=4)
    assert len(times) == 4 and len(calls) == 5 and all(t >= 0 for t in times)
    slow = median_ms(lambda: time.sleep(0.02), repeats=3)
    assert 15 < slow < 500  # milliseconds, not seconds
