"""The on-disk cache folder and content fingerprints (cache keys).

A layer of its own below everything that caches: ``mesh`` caches operators, ``rig`` caches
synthesised rigs, and neither needs the other for it.
"""

import hashlib
import os
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
