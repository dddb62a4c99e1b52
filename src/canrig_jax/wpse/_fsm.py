"""The fix-shape method (FSM), the baseline WPSE is compared with.

A fix shape c_s is sculpted at a corner of the weight hypercube (its trigger blendshapes at 1,
the rest at 0) and triggered by the product of its trigger weights (Seol et al., eq. (8)):

    f(w) = f_base(w) + sum_s (prod_{j in T_s} w_j) c_s,

which is exactly a corrective term of Racković's eq. (5), so a fix-shape rig is a
``BlendshapeRig`` with one more corrective table, and ``evaluate`` runs it. Fix shapes are
placed only at corners: in-between poses get the product of fractional weights times the
corner sculpt, and weights above 1 overshoot polynomially.
"""

from collections.abc import Callable, Sequence

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from .._checks import check_real
from ..rig import MUTUALLY_EXCLUSIVE, BlendshapeRig, Corrective, evaluate_batch, exclusive_pairs


def coactivation_pairs(
    animation: Float[ArrayLike, "T K"],
    n_pairs: int,
    names: Sequence[str] = (),
    exclude: Sequence[tuple[str, str]] = MUTUALLY_EXCLUSIVE,
) -> Int[np.ndarray, "N 2"]:
    """The ``n_pairs`` blendshape pairs that co-activate most in an animation.

    The score of a pair (a, b) is sum_t w_{t,a} w_{t,b}, the total of its FSM trigger over the
    frames; pairs named in ``exclude`` (opposite directions of one control, matched by
    canonical ARKit name as in ``rig.exclusive_pairs``, so ``names`` may be ICT, ARKit or
    Unreal spellings) and pairs that never co-activate are skipped. Returns (N, 2) indices,
    N <= n_pairs, best first.
    """
    animation = np.asarray(animation, np.float64)
    if animation.ndim != 2 or animation.shape[0] == 0:
        raise ValueError(f"animation: expected shape (T, K) with T >= 1, got {animation.shape}")
    if not np.all(np.isfinite(animation)):
        raise ValueError("animation: contains non-finite values")
    if n_pairs < 1:
        raise ValueError(f"n_pairs: expected >= 1, got {n_pairs}")
    k = animation.shape[1]
    if names and len(names) != k:
        raise ValueError(f"names: expected {k} names, got {len(names)}")
    score = animation.T @ animation
    a, b = np.triu_indices(k, 1)
    keep = score[a, b] > 0
    if names:
        banned = set(exclusive_pairs(names, exclude))  # canonical ARKit names, any spelling
        keep &= np.array([(i, j) not in banned for i, j in zip(a, b, strict=True)], bool)
    a, b, s = a[keep], b[keep], score[a, b][keep]
    order = np.argsort(-s, kind="stable")[:n_pairs]
    return np.stack([a[order], b[order]], axis=1).astype(np.int32)


def fix_shape_rig(
    rig: BlendshapeRig,
    triggers: Int[ArrayLike, "N n"],
    sculpt: Callable[[Float[np.ndarray, "B K"]], Float[ArrayLike, "B V 3"]],
) -> BlendshapeRig:
    """``rig`` plus one fix shape per row of ``triggers``, sculpted at its corner.

    Args:
        rig: the base rig (it must not already hold correctives of the trigger order).
        triggers: (N, n) blendshape indices, n >= 2 distinct per row.
        sculpt: the desired mesh at a batch of poses, (B, K) -> (B, V, 3) in rig units
            (e.g. a ``DeformationGradientBlend``); fix shape = sculpt(corner) - rig(corner).
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if not callable(sculpt):
        raise TypeError(f"sculpt: expected a function of poses, got {type(sculpt).__name__}")
    triggers = np.asarray(triggers)
    if triggers.size and not np.issubdtype(triggers.dtype, np.integer):
        raise TypeError(f"triggers: expected integer blendshape indices, got {triggers.dtype}")
    triggers = triggers.astype(np.int32)
    if triggers.ndim != 2 or triggers.shape[0] == 0 or triggers.shape[1] < 2:
        raise ValueError(
            f"triggers: expected shape (N, n) with N >= 1, n >= 2, got {triggers.shape}"
        )
    k = rig.n_blendshapes
    if triggers.min() < 0 or triggers.max() >= k:
        raise ValueError(f"triggers: indices must lie in [0, {k})")
    rows = np.sort(triggers, axis=1)
    if np.any(rows[:, 1:] == rows[:, :-1]):
        bad = np.flatnonzero(np.any(rows[:, 1:] == rows[:, :-1], axis=1))[:5]
        raise ValueError(f"triggers: rows {bad.tolist()} repeat a blendshape index")
    if rig.corrective(triggers.shape[1]) is not None:
        raise ValueError(
            f"rig: already has order-{triggers.shape[1]} correctives; fix shapes of that order "
            "would need a second table"
        )
    corners = np.zeros((triggers.shape[0], k), np.float32)
    np.put_along_axis(corners, triggers, 1.0, axis=1)
    desired = np.asarray(sculpt(corners))
    if desired.shape != (triggers.shape[0], rig.n_vertices, 3):
        raise ValueError(
            f"sculpt: expected meshes of shape ({triggers.shape[0]}, {rig.n_vertices}, 3), "
            f"got {desired.shape}"
        )
    check_real("sculpt", desired)
    desired = desired.astype(np.float32)
    if not np.all(np.isfinite(desired)):
        bad = np.flatnonzero(~np.all(np.isfinite(desired), axis=(1, 2)))[:5]
        raise ValueError(
            f"sculpt: returned non-finite positions at the corners of triggers {bad.tolist()}"
        )
    base = np.asarray(evaluate_batch(rig, corners))
    table = Corrective.from_dense(triggers, desired - base)  # raises on repeated indices
    return BlendshapeRig(
        rig.neutral, rig.deltas, (*rig.correctives, table), rig.names, rig.faces, units=rig.units
    )
