"""Table 1 of Seol et al. for one mesh and one edit library: how long a pose-space edit takes
to train and to run per frame, in JAX and in the NumPy reference, beside the rig itself."""

import time

import jax
import numpy as np
from jaxtyping import ArrayLike, Float

from ...rig import BlendshapeRig, evaluate, evaluate_batch
from ...wpse._pse import fit_pose_space_edit
from ._reference import time_runtime


def time_edit_model(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "P K"],
    edits: Float[ArrayLike, "P V 3"],
    probe: Float[ArrayLike, "T K"],
    *,
    sigma: float,
    support_tol: float = 0.0,
) -> dict:
    """Train a WPSE model of ``edits`` (twice: the first call compiles) and time it on the
    ``probe`` frames (``time_runtime``) and the rig's own ``evaluate`` on the same frames.

    Args:
        rig: the base rig; poses, edits: the edit library (as for ``fit_pose_space_edit``).
        probe: (T, K) frames to run; sigma, support_tol: as for ``fit_pose_space_edit``.

    Returns a row: ``vertices``, ``edited_vertices`` (the model's support), ``edits``,
    ``train_s`` and ``first_train_s_with_compile`` (seconds), ``runtime_ms`` and
    ``runtime_min_ms`` (median and minimum per frame of jitted ``apply``),
    ``numpy_runtime_ms``, ``batched_runtime_ms`` (per frame of ``vmap`` over all T),
    ``rig_evaluate_ms`` (jitted ``evaluate`` per frame) and ``max_abs_diff_vs_numpy_cm``.
    """
    probe = np.asarray(probe)
    if probe.ndim != 2 or probe.shape[1] != rig.n_blendshapes or probe.shape[0] < 1:
        raise ValueError(f"probe: expected shape (T, {rig.n_blendshapes}), got {probe.shape}")
    posed = np.asarray(evaluate_batch(rig, probe))

    def train():
        model = fit_pose_space_edit(rig, poses, edits, sigma=sigma, support_tol=support_tol)
        return jax.block_until_ready(model)

    start = time.perf_counter()
    model = train()
    first_train = time.perf_counter() - start
    start = time.perf_counter()
    model = train()
    train_s = time.perf_counter() - start
    timed = time_runtime(model, probe, posed)
    rig_eval = jax.jit(evaluate)
    jax.block_until_ready(rig_eval(rig, probe[0]))
    start = time.perf_counter()
    for w in probe:
        jax.block_until_ready(rig_eval(rig, w))
    rig_seconds = (time.perf_counter() - start) / len(probe)
    return {
        "vertices": rig.n_vertices,
        "edited_vertices": int(model.vertices.shape[0]),
        "edits": int(np.shape(poses)[0]),
        "train_s": train_s,
        "first_train_s_with_compile": first_train,
        "runtime_ms": 1e3 * float(np.median(timed["jax_seconds"])),
        "runtime_min_ms": 1e3 * float(np.min(timed["jax_seconds"])),
        "numpy_runtime_ms": 1e3 * float(np.median(timed["numpy_seconds"])),
        "batched_runtime_ms": 1e3 * timed["batched_seconds"],
        "rig_evaluate_ms": 1e3 * rig_seconds,
        "max_abs_diff_vs_numpy_cm": timed["max_abs_diff"],
    }
