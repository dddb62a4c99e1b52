"""The check of a triangle mesh, shared by everything in ``mesh`` and above it, and the typed
shape of a sparse operator."""

from typing import Any

import numpy as np
import scipy.sparse as sp
from jaxtyping import Float64, Int64


def check_vertices(vertices: Any, name: str = "vertices") -> Float64[np.ndarray, "V 3"]:
    """Validate (V, 3) vertex positions, V > 0, real and finite; return them as float64.

    Raises ValueError naming the argument ``name`` (the caller's name for the positions,
    e.g. ``neutral``)."""
    vertices = np.asarray(vertices)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"{name}: expected shape (V, 3) with V > 0, got {vertices.shape}")
    if not np.issubdtype(vertices.dtype, np.number) or np.iscomplexobj(vertices):
        raise ValueError(f"{name}: expected real numbers, got dtype {vertices.dtype}")
    vertices = vertices.astype(np.float64)
    if not np.all(np.isfinite(vertices)):
        bad = np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))[:5]
        raise ValueError(f"{name}: non-finite positions at vertices {bad.tolist()}")
    return vertices


def check_mesh(
    vertices: Any, faces: Any, *, name: str = "vertices"
) -> tuple[Float64[np.ndarray, "V 3"], Int64[np.ndarray, "F 3"]]:
    """Validate a triangle mesh; return (V, 3) float64 vertices and (F, 3) int64 faces.

    Raises ValueError naming the positions' argument ``name`` or ``faces`` for a wrong
    shape, non-finite positions, no faces, or face indices outside [0, V).
    """
    vertices = check_vertices(vertices, name)
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3) triangles, got {faces.shape}")
    if faces.shape[0] == 0:
        raise ValueError("faces: the mesh has no faces")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces: expected integer vertex indices, got dtype {faces.dtype}")
    faces = faces.astype(np.int64)
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= vertices.shape[0]:
        raise ValueError(
            f"faces: vertex indices must lie in [0, {vertices.shape[0]}) (the vertex count), "
            f"found range [{lo}, {hi}]"
        )
    return vertices, faces


def sparse_shape(matrix: sp.spmatrix) -> tuple[int, int]:
    """(rows, columns) of a SciPy sparse matrix (its ``shape``, typed)."""
    rows, columns = matrix.shape
    return int(rows), int(columns)
