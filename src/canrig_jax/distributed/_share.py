"""Independent work shared across processes: each does a contiguous share, all get the whole.

``gather_frames(fn, batch)`` runs ``fn`` on this process's share of a batch's leading axis
(frames of a take) and gathers every process's outputs in frame order; ``map_items(fn, items)``
does the same for a list whose results differ in shape (heads of different meshes). Every
process must call them with the same inputs; each returns the same whole result in every
process. With one process they are ``fn(batch)`` and ``[fn(x) for x in items]``.
"""

import pickle
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

T = TypeVar("T")
R = TypeVar("R")


def process_share(n: int, processes: int | None = None, process_id: int | None = None) -> slice:
    """The items ``[start, stop)`` of ``n`` that process ``process_id`` of ``processes``
    (default: this run's) handles: contiguous shares of ``ceil(n / processes)``, the last ones
    shorter or empty."""
    processes = jax.process_count() if processes is None else processes
    process_id = jax.process_index() if process_id is None else process_id
    if n < 0:
        raise ValueError(f"n: expected a non-negative count, got {n}")
    size = -(-n // processes)
    start = min(process_id * size, n)
    return slice(start, min(start + size, n))


def _leading(batch) -> int:
    sizes = {np.shape(leaf)[0] for leaf in jax.tree_util.tree_leaves(batch) if np.ndim(leaf)}
    if len(sizes) != 1:
        raise ValueError(
            f"batch: expected array leaves sharing one leading (frame) axis, got sizes "
            f"{sorted(sizes) if sizes else 'none'}"
        )
    (n,) = sizes
    if n == 0:
        raise ValueError("batch: expected at least one frame")
    return n


def gather_frames(fn: Callable[[T], Any], batch: T, *, chunk: int | None = None) -> Any:
    """``fn(batch)`` computed in shares across processes: ``fn`` maps a batch (a pytree of
    arrays with one leading frame axis of length n) to outputs with the same leading axis,
    frame by frame (frames must not depend on each other). The frames are cut into chunks of
    ``chunk`` (default: one equal share per process), the last padded with copies of the last
    frame so that ``fn`` compiles once; each process runs ``fn`` on its contiguous run of
    chunks and the outputs are gathered in frame order: every process returns the whole
    result, (n, ...) leaves as its own JAX arrays.

    A fixed ``chunk`` makes every frame's result independent of the process count, bit for
    bit: each chunk is the same call on the same frames wherever it runs (a batched float32
    solve otherwise rounds differently with the batch's size). One process and no
    ``chunk``: ``fn(batch)``."""
    n = _leading(batch)
    processes, me = jax.process_count(), jax.process_index()
    if chunk is None:
        if processes == 1:
            return fn(batch)
        chunk = -(-n // processes)
    if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
        raise ValueError(f"chunk: expected a positive number of frames, got {chunk!r}")
    n_chunks = -(-n // chunk)
    per_process = -(-n_chunks // processes)
    frames = np.minimum(np.arange(per_process * processes * chunk), n - 1)
    mine = frames.reshape(processes, per_process, chunk)[me]
    # jnp.take: typed PRNG keys have no NumPy form
    outputs = [
        fn(jax.tree_util.tree_map(lambda x, i=i: jnp.take(x, i, axis=0), batch)) for i in mine
    ]
    local = jax.tree_util.tree_map(lambda *parts: jnp.concatenate(parts), *outputs)
    if processes > 1:
        local = multihost_utils.process_allgather(local, tiled=True)
    return jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf)[:n], local)


def _host(tree):
    """JAX array leaves as NumPy (picklable without a device)."""
    return jax.tree_util.tree_map(
        lambda leaf: np.asarray(leaf) if isinstance(leaf, jax.Array) else leaf, tree
    )


def map_items(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(x) for x in items]`` computed in shares across processes: each process runs ``fn``
    on its ``process_share`` of ``items``, and the results (any picklable values; JAX arrays
    come back as NumPy arrays) are gathered in order, so every process returns the whole
    list. For work whose results differ in shape, e.g. one rig per head. One process: the
    plain list."""
    items = list(items)
    if jax.process_count() == 1:
        return [fn(x) for x in items]
    mine = [_host(fn(x)) for x in items[process_share(len(items))]]
    payload = np.frombuffer(pickle.dumps(mine, protocol=pickle.HIGHEST_PROTOCOL), np.uint8)
    sizes = np.asarray(multihost_utils.process_allgather(np.int32(payload.size))).ravel()
    padded = np.zeros(int(sizes.max()), np.uint8)
    padded[: payload.size] = payload
    every = np.asarray(multihost_utils.process_allgather(padded))
    results: list[Any] = []
    for row, size in zip(every, sizes, strict=True):
        results.extend(pickle.loads(row[: int(size)].tobytes()))
    return results
