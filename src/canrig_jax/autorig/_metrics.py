"""Evaluation of generated rigs: vertex errors and inner-part penetration."""

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._metrics import CM_TO_MM


@jax.jit
def winding_numbers(
    points: Float[Array, "N 3"], triangles: Float[Array, "T 3 3"]
) -> Float[Array, " N"]:
    """Generalised winding number of each point w.r.t. a triangle soup (Jacobson et al.
    2013): the sum of signed solid angles (Van Oosterom & Strackee) over 4 pi. About +-1
    inside a closed, consistently oriented surface, 0 outside, fractional near holes."""

    def one(p):
        a, b, c = (triangles[:, i] - p for i in range(3))
        la, lb, lc = (jnp.linalg.norm(x, axis=1) for x in (a, b, c))
        numerator = jnp.sum(a * jnp.cross(b, c), axis=1)
        denominator = (
            la * lb * lc
            + jnp.sum(a * b, axis=1) * lc
            + jnp.sum(a * c, axis=1) * lb
            + jnp.sum(b * c, axis=1) * la
        )
        return jnp.sum(2.0 * jnp.arctan2(numerator, denominator)) / (4.0 * jnp.pi)

    return jax.lax.map(one, points, batch_size=32)


@jax.jit
def _pose_winding_numbers(posed, inner_index, enclosing):
    """(P, N) winding numbers of the ``inner_index`` vertices of each posed mesh w.r.t. its
    ``enclosing`` triangles (jitted once per shape, not per call)."""
    return jax.lax.map(lambda v: winding_numbers(v[inner_index], v[enclosing]), posed)


def outside_fraction(
    vertices: Float[ArrayLike, "*P V 3"],
    faces: Int[ArrayLike, "F 3"],
    inner: Bool[ArrayLike, " V"],
    enclosing_faces: Bool[ArrayLike, " F"],
) -> Float[np.ndarray, "*P"]:
    """Per pose, the fraction of ``inner`` vertices (bool (V,)) whose winding number w.r.t.
    the ``enclosing_faces`` (bool (F,)) of the same mesh is below one half in magnitude,
    i.e. that lie outside the enclosing surface.

    Args:
        vertices: (V, 3) one mesh or (P, V, 3) several poses of it.

    Returns:
        (P,) fractions (a 0-d array for one mesh).
    """
    inner = np.asarray(inner, bool)
    if not inner.any():
        raise ValueError("inner: no inner-part vertices to test")
    enclosing = np.asarray(faces)[np.asarray(enclosing_faces, bool)]
    if enclosing.shape[0] == 0:
        raise ValueError("enclosing_faces: selects no triangles")
    posed = jnp.asarray(vertices, jnp.float32)
    single = posed.ndim == 2
    posed = posed[None] if single else posed
    w = _pose_winding_numbers(posed, jnp.asarray(np.flatnonzero(inner)), jnp.asarray(enclosing))
    fraction = np.mean(np.abs(np.asarray(w)) < 0.5, axis=1)
    return fraction[0] if single else fraction


def inner_outside(
    head: Any, displacements: Float[ArrayLike, "P V 3"], part_names: Sequence[str]
) -> Bool[np.ndarray, "P N"]:
    """(P, N) bool: which inner-part vertices (teeth, gums, eyeballs; N of them, in vertex
    order) lie outside the skin (face, head and neck) of ``head`` posed by each of
    ``displacements`` (P, V, 3)."""
    from ..data import ENCLOSING_PARTS, INNER_PARTS

    index = lambda parts: [list(part_names).index(p) for p in parts]  # noqa: E731
    inner = np.isin(head.parts, index(INNER_PARTS))
    if not inner.any():
        raise ValueError("head: no inner-part vertices to test")
    skin = np.isin(head.parts, index(ENCLOSING_PARTS))[head.faces].all(axis=1)
    if not skin.any():
        raise ValueError("head: no skin triangles enclose the inner parts")
    posed = jnp.asarray(head.vertices[None] + np.asarray(displacements), jnp.float32)
    w = _pose_winding_numbers(
        posed, jnp.asarray(np.flatnonzero(inner)), jnp.asarray(np.asarray(head.faces)[skin])
    )
    return np.abs(np.asarray(w)) < 0.5


def penetration(
    head: Any, displacements: Float[ArrayLike, "P V 3"], part_names: Sequence[str]
) -> float:
    """Mean over poses of the fraction of inner-part vertices (teeth, gums, eyeballs) outside
    the skin (face, head and neck) of ``head`` posed by ``displacements`` (P, V, 3)."""
    return float(inner_outside(head, displacements, part_names).mean())


def penetration_free_set(
    head: Any,
    part_names: Sequence[str],
    truth: Float[ArrayLike, "P V 3"] | None = None,
    *,
    threshold: float = 0.0,
) -> tuple[Int[np.ndarray, " Q"], Bool[np.ndarray, " N"]]:
    """Where the ground truth has no penetration (Table 3 of RigAnyFace, made separable):
    the inner-part vertices inside the skin at rest (this leaves out e.g. the fronts of the
    eyeballs that show through the eye openings) and the poses whose ground truth puts at
    most ``threshold`` of them outside (default 0: none).

    Args:
        head: a head with ``vertices``, ``faces``, ``parts`` (and ``displacements``).
        truth: (P, V, 3) ground-truth displacements (default ``head.displacements``).

    Returns ((Q,) pose indices, (N,) bool mask over the inner vertices of ``inner_outside``).
    Measured with ``inner_outside(...)[poses][:, vertices]``, the ground truth scores 0
    (threshold 0) and so does the neutral head.
    """
    truth = np.asarray(head.displacements if truth is None else truth)
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"threshold: expected a fraction in [0, 1), got {threshold}")
    rest = inner_outside(head, np.zeros((1, *np.shape(head.vertices))), part_names)[0]
    vertices = ~rest
    outside = inner_outside(head, truth, part_names)[:, vertices]
    poses = np.flatnonzero(outside.mean(axis=1) <= threshold)
    return poses, vertices


def error_stats(
    predicted: Float[ArrayLike, "*P V 3"], truth: Float[ArrayLike, "*P V 3"], scale: float = 1.0
) -> dict:
    """{"mae_mm", "q95_mm"} of per-vertex distances over all poses; inputs in centimetres,
    or in unit-sphere units with ``scale`` the head's cm per unit."""
    distance = np.linalg.norm(np.asarray(predicted) - np.asarray(truth), axis=-1) * scale
    return {
        "mae_mm": float(distance.mean() * CM_TO_MM),
        "q95_mm": float(np.percentile(distance, 95) * CM_TO_MM),
    }
