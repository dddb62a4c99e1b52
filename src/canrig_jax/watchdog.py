"""A watchdog for long runs: no progress for too long ends the process with a clear error and
every thread's stack, never silence.

A compiled call that never returns (a deadlock in a native library, a solver that stopped
making progress) would otherwise leave a command or an experiment waiting forever. The ``canrig``
command and the experiments run their work inside ``watchdog``; long loops report ``progress``.
When ``seconds`` pass without any, the watchdog prints what it was waiting for, dumps the stack
of every thread (``faulthandler``) to standard error and exits with status ``EXIT_STATUS``. A
second, native timer (``faulthandler.dump_traceback_later``) fires ``GRACE`` seconds later in
case the Python interpreter itself is blocked.

    from canrig_jax.watchdog import watchdog, progress

    with watchdog(600, "fit the take"):
        for frame in frames:
            ...
            progress(f"frame {i}")

``CANRIG_WATCHDOG`` (seconds; 0 disables) sets the limit of the command line.
"""

import contextlib
import faulthandler
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import TypeVar

_T = TypeVar("_T")

EXIT_STATUS = 70
"""The process's exit status when the watchdog fires (EX_SOFTWARE)."""

GRACE = 30.0
"""Seconds after the limit at which the native timer ends a process whose interpreter is stuck."""

REARM = 1.0
"""Seconds between two re-armings of the native timer (it fires up to this much early,
well inside ``GRACE``)."""

_active: "list[Watchdog]" = []


class Watchdog:
    """The timer of one ``watchdog`` block (see the module docstring)."""

    def __init__(self, seconds: float, what: str):
        if not (seconds > 0 and seconds < float("inf")):
            raise ValueError(f"seconds: expected a finite limit > 0, got {seconds}")
        self.seconds = float(seconds)
        self.what = what
        self.last = "start"
        self._lock = threading.Lock()
        self._deadline = time.monotonic() + self.seconds
        self._armed: float | None = None  # when the native timer was last armed
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="canrig-watchdog", daemon=True)

    def progress(self, step: str = "") -> None:
        """Reset the timer; ``step`` names what was last done (shown if it fires)."""
        now = time.monotonic()
        with self._lock:
            self._deadline = now + self.seconds
            self.last = step or self.last
            rearm = self._armed is None or now - self._armed > REARM
            if rearm:
                self._armed = now
        native = _native_stderr()
        # re-arming restarts faulthandler's thread: at most once a REARM (a training loop
        # reports every step); none under a capturing test runner (the Python timer remains)
        if rearm and native is not None:
            faulthandler.dump_traceback_later(self.seconds + GRACE, exit=True, file=native)

    def _watch(self) -> None:
        while not self._stop.wait(min(1.0, self.seconds / 4)):
            with self._lock:
                late = time.monotonic() > self._deadline
            if late:
                print(
                    f"canrig: error: no progress for {self.seconds:.0f} s in {self.what} "
                    f"(last step: {self.last}); the call is stuck. Stacks of every thread "
                    f"follow; please report them.",
                    file=sys.stderr,
                    flush=True,
                )
                _dump_stacks()
                os._exit(EXIT_STATUS)

    def __enter__(self) -> "Watchdog":
        _active.append(self)
        self.progress("start")
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        _active.remove(self)
        faulthandler.cancel_dump_traceback_later()
        if _active:  # an enclosing watchdog keeps watching: its native timer was cancelled
            _active[-1]._armed = None
            _active[-1].progress()


def _native_stderr():
    """Standard error as a file with a descriptor (what ``faulthandler`` writes to), or None."""
    for stream in (sys.stderr, sys.__stderr__):
        if stream is None:
            continue
        try:
            stream.fileno()
            return stream
        except (AttributeError, OSError, ValueError):
            continue
    return None


def _dump_stacks() -> None:
    """Every thread's stack on standard error."""
    native = _native_stderr()
    if native is not None:
        native.flush()
        faulthandler.dump_traceback(file=native, all_threads=True)
        native.flush()
        return
    for ident, frame in sys._current_frames().items():
        print(f"Thread {ident:#x}:", "".join(traceback.format_stack(frame)), file=sys.stderr)
    sys.stderr.flush()


def watchdog(
    seconds: float | None, what: str = "this run"
) -> "Watchdog | contextlib.nullcontext[None]":
    """A context that watches its block: when ``seconds`` pass without ``progress``, it prints
    ``what`` and the last step reported, dumps every thread's stack and exits with
    ``EXIT_STATUS`` (module docstring). It yields the block's timer, whose ``progress(step)``
    is ``progress`` for this block. ``None`` or 0 watches nothing (yields None)."""
    if not seconds:
        return contextlib.nullcontext()
    return Watchdog(seconds, what)


def progress(step: str = "") -> None:
    """Report progress to the innermost active watchdog (a no-op outside one)."""
    if _active:
        _active[-1].progress(step)


def limit_from_environment(default: float) -> float | None:
    """``CANRIG_WATCHDOG`` in seconds (0: off), else ``default``; a bad value is an error."""
    value = os.environ.get("CANRIG_WATCHDOG")
    if value is None:
        return default
    try:
        seconds = float(value)
    except ValueError:
        raise ValueError(f"CANRIG_WATCHDOG: expected seconds, got {value!r}") from None
    if not (seconds >= 0 and seconds < float("inf")):
        raise ValueError(f"CANRIG_WATCHDOG: expected seconds >= 0, got {value!r}")
    return seconds or None


DEFAULT_LIMIT = 1800.0
"""Seconds without progress after which the command line and the experiments give up
(``CANRIG_WATCHDOG`` overrides): above the longest compilation and the longest step between
two progress reports seen here (operators of a large head, an evaluation pass)."""


def run_watched(main: Callable[..., _T], what: str, *args, **kwargs) -> _T:
    """``main(*args, **kwargs)`` inside ``watchdog(limit_from_environment(DEFAULT_LIMIT), what)``:
    how the ``canrig`` command and the experiments run."""
    with watchdog(limit_from_environment(DEFAULT_LIMIT), what):
        return main(*args, **kwargs)


__all__ = ["EXIT_STATUS", "progress", "run_watched", "watchdog"]
