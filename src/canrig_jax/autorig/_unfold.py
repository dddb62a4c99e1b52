"""Unfolding generated shapes: triangles a shape turns inside out are smoothed away.

A transferred or predicted shape can fold a few triangles where the head's mesh and the
template's disagree most: the tiny triangles of an eye corner, the inner corners of the
mouth. A rigger smooths such spots by hand. ``unfold_shapes`` does it for every single
shape: where a triangle's normal turns against its neutral normal at weight 1 or 1/2
(``mesh.flipped_triangles``), its corners' deltas are replaced by the mean of their
neighbours' (one Jacobi step of Laplacian smoothing on those vertices only), round after
round until no triangle turns or ``UNFOLD_ROUNDS`` rounds have run. Vertices away from a
fold keep their deltas exactly.
"""

import numpy as np
import scipy.sparse as sp
from jaxtyping import Float, Int

from ..mesh import flipped_triangles
from ..mesh._topology import vertex_adjacency
from ..rig import BlendshapeRig

UNFOLD_ROUNDS = 30
"""Smoothing rounds at most per shape."""

UNFOLD_WEIGHTS = (1.0, 0.5)
"""The weights at which a shape must turn no triangle."""


def unfold_deltas(
    neutral: Float[np.ndarray, "V 3"],
    faces: Int[np.ndarray, "F 3"],
    deltas: Float[np.ndarray, "K V 3"],
    *,
    rounds: int = UNFOLD_ROUNDS,
) -> tuple[Float[np.ndarray, "K V 3"], Int[np.ndarray, " K"]]:
    """(the deltas unfolded (float64, the units of ``neutral``), (K,) triangles each shape
    still turns at any of ``UNFOLD_WEIGHTS`` after the last round)."""
    neutral = np.asarray(neutral, np.float64)
    deltas = np.array(deltas, np.float64)
    faces = np.asarray(faces, np.int64)
    adjacency = vertex_adjacency(faces, len(neutral))
    degree = np.maximum(np.asarray(adjacency.sum(axis=1)).ravel(), 1.0)
    average = sp.diags(1.0 / degree) @ adjacency

    def folded(d):  # (K, V) bool: corners of triangles turned at some weight
        turned = np.zeros((d.shape[0], len(faces)), bool)
        for w in UNFOLD_WEIGHTS:
            turned |= flipped_triangles(neutral + w * d, neutral, faces)
        corners = np.zeros((d.shape[0], len(neutral)), bool)
        for k in np.flatnonzero(turned.any(axis=1)):
            corners[k, faces[turned[k]].ravel()] = True
        return corners, turned.sum(axis=1)

    corners, left = folded(deltas)
    for _ in range(rounds):
        active = np.flatnonzero(corners.any(axis=1))
        if active.size == 0:
            break
        smooth = average @ np.moveaxis(deltas[active], 0, 1).reshape(len(neutral), -1)
        smooth = np.moveaxis(smooth.reshape(len(neutral), active.size, 3), 1, 0)
        deltas[active] = np.where(corners[active, :, None], smooth, deltas[active])
        corners[active], left[active] = folded(deltas[active])
    return deltas, left


def unfold_shapes(
    rig: BlendshapeRig, keep: tuple[str, ...] = ()
) -> tuple[BlendshapeRig, dict[str, int]]:
    """``rig`` with every single shape unfolded (``unfold_deltas``; correctives, and the
    shapes named in ``keep`` (an artist's examples), as they are), and {shape name:
    triangles it still turns} for the shapes not fully unfolded."""
    mine = np.array([str(n) not in keep for n in rig.names])
    deltas = np.array(rig.deltas, np.float64)
    left = np.zeros(len(mine), np.int64)
    if mine.any():
        deltas[mine], left[mine] = unfold_deltas(
            np.asarray(rig.neutral), np.asarray(rig.faces), deltas[mine]
        )
    out = BlendshapeRig(
        rig.neutral,
        deltas.astype(np.float32),
        rig.correctives,
        rig.names,
        rig.faces,
        rig.units,
    )
    return out, {str(n): int(c) for n, c in zip(rig.names, left, strict=True) if c}
