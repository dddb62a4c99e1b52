"""Edit reuse by search (Seol et al., section 4, eq. 7): a library of sculpted edits corrects
new frames through the edits that the region-of-interest search finds for each frame.

For every query pose, ``search_edits`` keeps the library edits with E < tau on the region;
a WPSE model of those edits alone (one per distinct set found, cached) corrects the frame.
A frame for which the search finds nothing is left uncorrected.
"""

import dataclasses

import jax
import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ..rig import BlendshapeRig, evaluate_batch
from ._metric import blendshape_metric
from ._pse import apply, check_edits, check_sigma, fit_pose_space_edit
from ._search import search_edits


@dataclasses.dataclass(frozen=True)
class ReuseResult:
    """Result of ``reuse_edits`` (its docstring lists the fields)."""

    corrections: Float[np.ndarray, "T V 3"]
    found: tuple[Int[np.ndarray, " _n"], ...]


def reuse_edits(
    rig: BlendshapeRig,
    library_poses: Float[ArrayLike, "N K"],
    library_edits: Float[ArrayLike, "N V 3"],
    query_poses: Float[ArrayLike, "T K"],
    roi: Int[ArrayLike, " R"],
    *,
    tau: float,
    sigma: float,
    **fit_kwargs,
) -> ReuseResult:
    """Correct every query frame with the library edits the search finds for it.

    Args:
        rig: the base rig (its metric ranks the library, its meshes carry the local frames).
        library_poses, library_edits: the stored edits, as for ``fit_pose_space_edit``.
        query_poses: (T, K) frames to correct.
        roi: region of interest of the search (vertex indices).
        tau: search threshold on E (eq. 7; > 0).
        sigma: Gaussian width of the models built from the found edits.
        fit_kwargs: passed to ``fit_pose_space_edit`` (``support_tol``, ``rest_pose``, ...).

    Returns:
        A ``ReuseResult``: ``corrections`` (T, V, 3), the world-space correction of every
        query frame by the edits found for it, and ``found``, the library indices used at
        each frame (best first).
    """
    if not isinstance(rig, BlendshapeRig):
        raise ValueError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    library_poses, library_edits = check_edits(rig, library_poses, library_edits)
    query_poses = np.asarray(query_poses, np.float32)
    if query_poses.ndim != 2 or query_poses.shape[1] != rig.n_blendshapes:
        raise ValueError(
            f"query_poses: expected shape (T, {rig.n_blendshapes}), got {query_poses.shape}"
        )
    if not np.all(np.isfinite(query_poses)):
        raise ValueError("query_poses: contains non-finite values")
    roi = np.asarray(roi)
    if (
        roi.ndim != 1
        or roi.size == 0
        or not np.issubdtype(roi.dtype, np.integer)
        or roi.min() < 0
        or roi.max() >= rig.n_vertices
    ):
        raise ValueError(
            f"roi: expected a non-empty 1-D set of vertex indices in [0, {rig.n_vertices})"
        )
    if not tau > 0:
        raise ValueError(f"tau: expected a value > 0, got {tau}")
    check_sigma(sigma)
    metric = blendshape_metric(rig.deltas)
    posed = np.asarray(evaluate_batch(rig, query_poses))
    corrections = np.zeros_like(posed)
    found, models = [], {}
    run = jax.jit(apply)
    for t, query in enumerate(query_poses):
        hits = search_edits(metric, library_poses, query, roi, tau).indices
        found.append(hits)
        if hits.size == 0:
            continue
        key = tuple(sorted(hits.tolist()))
        if key not in models:
            chosen = np.asarray(key)
            models[key] = fit_pose_space_edit(
                rig,
                library_poses[chosen],
                library_edits[chosen],
                sigma=sigma,
                **fit_kwargs,
            )
        corrections[t] = np.asarray(run(models[key], query, posed[t])) - posed[t]
    return ReuseResult(corrections, tuple(found))
