"""Triangles from polygons with up to four corners (quads and triangles mixed)."""

import numpy as np
from jaxtyping import Int


def triangulate_quads(polys: Int[np.ndarray, "F 4"]) -> Int[np.ndarray, "T 3"]:
    """(T, 3) int32 triangles of quads and triangles, each quad (a, b, c, d) fan-split into
    (a, b, c), (a, c, d), in polygon order.

    A row is a triangle when its fourth index is negative (ICT's ``polys``) or repeats one
    of the first three (the convention of OBJ exporters that pad triangles). Raises a
    ValueError naming ``polys`` for another shape, non-integer values, negative corners or
    a quad that repeats a corner.
    """
    polys = np.asarray(polys)
    if polys.ndim != 2 or polys.shape[1] != 4:
        raise ValueError(f"polys: expected shape (F, 4), got {polys.shape}")
    if polys.size and not np.issubdtype(polys.dtype, np.integer):
        raise ValueError(f"polys: expected integer vertex indices, got dtype {polys.dtype}")
    polys = polys.astype(np.int64)
    if np.any(polys[:, :3] < 0):
        raise ValueError("polys: the first three corners of every polygon must be >= 0")
    first = polys[:, :3]
    triangle = (polys[:, 3] < 0) | np.any(first == polys[:, 3:], axis=1)
    degenerate = (
        (first[:, 0] == first[:, 1]) | (first[:, 1] == first[:, 2]) | (first[:, 0] == first[:, 2])
    )
    if np.any(degenerate):
        rows = np.flatnonzero(degenerate)[:5].tolist()
        raise ValueError(f"polys: rows {rows} repeat a corner among their first three")
    second = np.where(triangle[:, None], -1, polys[:, [0, 2, 3]])
    out = np.stack([first, second], axis=1).reshape(-1, 3)  # interleaved: polygon order
    return out[out[:, 0] >= 0].astype(np.int32)
