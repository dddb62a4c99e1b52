"""One BLAS thread while a compiled program runs LAPACK.

jaxlib's CPU linear algebra (Cholesky, eigh, solves) calls the LAPACK that SciPy ships
(OpenBLAS), whose threads then compete with XLA's own thread pool. On this 2-core machine that
made a CANRig fit 4x slower (797 ms against 205 ms with ``OPENBLAS_NUM_THREADS=1``, measured in
``benchmarks/bench_canrig.py``). ``single_threaded_blas`` limits the BLAS pools
(``threadpoolctl``) for the duration of a block, restoring them after; the block must wait for
its results (JAX dispatches asynchronously).
"""

import contextlib
from collections.abc import Callable, Iterator
from typing import TypeVar

import jax
from threadpoolctl import threadpool_limits

T = TypeVar("T")


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Context: BLAS/LAPACK pools limited to one thread; restored on exit."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def blocking_single_threaded_blas(fn: Callable[..., T], *args, **kwargs) -> T:
    """``fn(*args, **kwargs)`` with one BLAS thread, waiting for its (pytree) result."""
    with single_threaded_blas():
        return jax.block_until_ready(fn(*args, **kwargs))
