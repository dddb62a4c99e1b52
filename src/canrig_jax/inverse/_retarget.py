"""Retargeting a take from one set of controls onto another set on the same mesh.

A head may carry several control sets over one neutral (Rocketbox: ARKit, FACS action units,
SRanipal; ``rig.select_control_set``). Weight curves of one set become curves of another by
going through the mesh: the source rig's mesh at every frame is the target of an inverse rig
on the other set,

    w_target(t) = argmin_{w in [0, u]^K'} 1/2 ||f_target(w) - (n_target + f_source(w_source(t))
                  - n_source)||^2 + alpha 1^T w,

so the target's curves reproduce what the source showed, as far as its controls can.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PRNGKeyArray

from .._checks import check_real, is_concrete
from .._metrics import CM_TO_MM
from .._warnings import warn
from ..rig import UNIT_IN_CM, BlendshapeRig, evaluate_batch
from ._base import AbstractInverseMethod
from ._problem import _without_shapes, prepare
from ._solution import Solution
from ._solve import solve_sequence

NEUTRAL_TOL_MM = 0.1
"""Default largest distance (mm) between the two rigs' neutrals at any vertex."""


def _check_rigs(source_rig, target_rig, neutral_tol_mm) -> None:
    for name, rig in (("source_rig", source_rig), ("target_rig", target_rig)):
        if not isinstance(rig, BlendshapeRig):
            raise TypeError(f"{name}: expected a BlendshapeRig, got {type(rig).__name__}")
    if isinstance(neutral_tol_mm, bool) or not isinstance(neutral_tol_mm, int | float):
        raise TypeError(f"neutral_tol_mm: expected a number, got {neutral_tol_mm!r}")
    if not (np.isfinite(neutral_tol_mm) and neutral_tol_mm >= 0):
        raise ValueError(f"neutral_tol_mm: expected a finite distance >= 0, got {neutral_tol_mm}")
    if target_rig.n_vertices != source_rig.n_vertices:
        raise ValueError(
            f"target_rig: has {target_rig.n_vertices} vertices, source_rig "
            f"{source_rig.n_vertices}; retargeting needs both control sets on one mesh "
            "(load every shape of the file once and select the sets from it)"
        )
    if not (is_concrete(source_rig.neutral) and is_concrete(target_rig.neutral)):
        return
    source_cm = np.asarray(source_rig.neutral, np.float64) * UNIT_IN_CM[source_rig.units]
    target_cm = np.asarray(target_rig.neutral, np.float64) * UNIT_IN_CM[target_rig.units]
    distance = np.linalg.norm(source_cm - target_cm, axis=1) * CM_TO_MM
    worst = int(np.argmax(distance))
    if distance[worst] > neutral_tol_mm:
        raise ValueError(
            f"target_rig: its neutral lies {distance[worst]:.4g} mm from source_rig's at vertex "
            f"{worst} (units {target_rig.units!r} and {source_rig.units!r}; neutral_tol_mm = "
            f"{neutral_tol_mm}); retargeting needs both control sets on one mesh"
        )


def _check_weights(source_rig: BlendshapeRig, weights) -> np.ndarray:
    check_real("weights", weights)
    weights = np.asarray(weights)
    k = source_rig.n_blendshapes
    if weights.ndim != 2 or weights.shape[1] != k or weights.shape[0] < 1:
        raise ValueError(
            f"weights: expected shape (T, {k}) with T >= 1 frames of source_rig's {k} "
            f"controls, got {weights.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(weights).all(axis=1))
    if bad.size:
        raise ValueError(f"weights: frames {bad[:10].tolist()} contain non-finite values")
    return weights.astype(np.float32)


def retarget(
    source_rig: BlendshapeRig,
    weights: Float[ArrayLike, "T K_source"],
    target_rig: BlendshapeRig,
    method: AbstractInverseMethod,
    *,
    correctives: bool = True,
    warm_start: bool = False,
    neutral_tol_mm: float = NEUTRAL_TOL_MM,
    key: PRNGKeyArray | None = None,
) -> Solution:
    """Weight curves of ``target_rig``'s controls that reproduce ``source_rig`` driven by
    ``weights``, frame by frame, on one mesh.

    The source rig is evaluated at every frame (``rig.evaluate_batch``, jitted), its offsets
    from its neutral are converted to the target's units and added to the target's neutral,
    and that take is inverted on the target's controls with ``solve_sequence`` (one compiled
    call for the take).

    Args:
        source_rig: the rig the weights drive (any corrective order; units from ``units``).
        weights: (T, K_source) the source's weight curves, unitless, finite.
        target_rig: a rig of the same mesh: the same vertex count and neutral (within
            ``neutral_tol_mm`` after unit conversion), e.g. another control set of the same
            file (``rig.select_control_set``).
        method: any inverse-rig method (``METHODS``), e.g. ``QuarticNewton(alpha=0.0)``;
            ``alpha`` is in squared target units (cm^2 for a rig in cm).
        correctives: invert on the target's full rig (default) or on its linear part
            (``False``); the source is always evaluated in full.
        warm_start: each frame starts from the previous frame's weights (``solve_sequence``).
        neutral_tol_mm: largest distance (mm) allowed between the two neutrals at any vertex.
        key: PRNG key for methods with a random order (default ``jax.random.key(0)``).

    Returns:
        A ``Solution`` with a leading frame axis: ``weights`` (T, K_target) in
        ``target_rig.names`` order, ``objective`` (T,) in squared target units, ``result`` and
        ``stats`` per frame. A target blendshape with all-zero deltas cannot be solved for:
        its curve is 0 (with a warning naming it).

    Raises TypeError/ValueError naming the argument, before any compiled work: rigs that are
    not ``BlendshapeRig``s or not on one mesh, weights of the wrong shape or not finite, a
    method that is not an inverse-rig method.
    """
    _check_rigs(source_rig, target_rig, neutral_tol_mm)
    weights = _check_weights(source_rig, weights)
    if not isinstance(method, AbstractInverseMethod):
        raise TypeError(
            "method: expected an inverse-rig method object (e.g. inverse.QuarticNewton()), got "
            f"{type(method).__name__}"
        )
    for name, flag in (("correctives", correctives), ("warm_start", warm_start)):
        if not isinstance(flag, bool):
            raise TypeError(f"{name}: expected a bool, got {flag!r}")
    rig = target_rig if correctives else target_rig.linear()
    k = rig.n_blendshapes
    norms = np.linalg.norm(np.asarray(rig.deltas, np.float64).reshape(k, -1), axis=1)
    kept = np.flatnonzero(norms > 0)
    if kept.size == 0:
        raise ValueError("target_rig: every blendshape has all-zero deltas; nothing to solve for")
    if kept.size < k:
        zero = [rig.names[i] if rig.names else int(i) for i in np.flatnonzero(norms == 0)]
        warn(f"retarget: target_rig blendshapes {zero} have all-zero deltas; their curves are 0")
        rig = _without_shapes(rig, np.flatnonzero(norms == 0).tolist())
    # names and faces play no part in the solve: without them, every target of one shape
    # structure shares one compiled solve
    problem = prepare(BlendshapeRig(rig.neutral, rig.deltas, rig.correctives, (), None, rig.units))

    scale = UNIT_IN_CM[source_rig.units] / UNIT_IN_CM[target_rig.units]
    meshes = evaluate_batch(source_rig, weights)
    offsets = (meshes - source_rig.neutral) * scale
    targets = jnp.asarray(target_rig.neutral, offsets.dtype) + offsets
    solution = solve_sequence(problem, targets, method, warm_start=warm_start, key=key)
    if kept.size < k:
        full = jnp.zeros((weights.shape[0], k), solution.weights.dtype)
        solution = eqx.tree_at(
            lambda s: s.weights, solution, full.at[:, kept].set(solution.weights)
        )
    return solution


__all__ = ["NEUTRAL_TOL_MM", "retarget"]
