"""The on-disk cache folder and content fingerprints (cache keys).

A layer of its own below everything that caches: ``mesh`` caches operators, ``rig`` caches
synthesised rigs, and neither needs the other for it.
"""

import contextlib
import hashlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Shaped

CACHE_ENV_VAR = "CANRIG_CACHE"


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """Cache folder: ``path``, else ``$CANRIG_CACHE``, else ``~/.cache/canrig_jax``."""
    if path is not None:
        return Path(path)
    if os.environ.get(CACHE_ENV_VAR):
        return Path(os.environ[CACHE_ENV_VAR])
    return Path.home() / ".cache" / "canrig_jax"


def fingerprint(*arrays: Shaped[ArrayLike, "..."]) -> str:
    """SHA-256 of the arrays' dtypes, shapes and bytes (a cache key)."""
    digest = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype}{a.shape}".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


mesh_fingerprint = fingerprint
"""The fingerprint of a mesh's arrays (vertices, faces, ...): the same function by its old name."""


@contextlib.contextmanager
def build_lock(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` + ".lock" while building a cache entry: processes
    that want the same entry at once (test workers, ``canrig launch``) wait for the first to
    write it and then read it, instead of each building it again. Advisory (``fcntl.flock``);
    where it is missing (Windows) every process builds as before."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    lock = Path(str(path) + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
