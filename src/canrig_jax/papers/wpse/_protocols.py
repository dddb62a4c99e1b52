"""Held-out evaluation protocols of the WPSE experiment (``experiments/wpse.py``): edits
sculpted at a few frames of a take, every other frame held out, and the error of each method
against the mesh the artist wants there.

Meshes are in the rig's units (ICT: centimetres); errors are reported in millimetres. The
building blocks (which frames to edit, the locality measure, a take's steps) live in
``_protocol.py``; the probes of a model's behaviour away from the held-out frames (locality,
overshoot, layering, search) in ``_probes.py``.
"""

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence

import jax
import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ..._metrics import CM_TO_MM, per_vertex_distance
from ...rig import BlendshapeRig, evaluate, evaluate_batch
from ...wpse._fsm import coactivation_pairs, fix_shape_rig
from ...wpse._metric import blendshape_metric
from ...wpse._pse import (
    EditData,
    PoseSpaceEdit,
    apply,
    correction,
    fit_pose_space_edit,
    fit_prepared,
    prepare_edits,
)
from ...wpse._reuse import reuse_edits
from ...wpse._sigma import fit_sigma, gui_from_sigma
from ...wpse._temporal import temporal_change
from ...wpse._width import fit_width
from ._protocol import select_edit_frames

VARIANTS: dict[str, dict] = {
    "pse": {"metric": "euclidean", "local_frames": True, "rest_pose": False},
    "wpse": {"metric": "weighted", "local_frames": True, "rest_pose": False},
    "wpse_rest_pose": {"metric": "weighted", "local_frames": True, "rest_pose": True},
    "wpse_global_frames": {"metric": "weighted", "local_frames": False, "rest_pose": False},
}
"""The pose-space edit variants ``compare_methods`` fits (``prepare_edits`` options): plain
PSE (Euclidean weight distance), WPSE, WPSE with a zero edit pinned at the rest pose, WPSE with
its edits stored in world space instead of the posed mesh's local frames."""

SWEEP_FACTORS = np.geomspace(0.25, 2.0, 7)
"""Multiples of the leave-one-out width of the oracle sweep (1.0 among them)."""

Channels = Sequence[int] | Int[ArrayLike, " C"]
"""Blendshape indices: a list of ints or an integer array."""

Sculpt = Callable[[Float[np.ndarray, "*B K"]], Float[np.ndarray, "*B V 3"]]
"""The mesh the artist wants: NumPy weights (..., K) -> NumPy meshes (..., V, 3) in rig
units (e.g. ``mesh.DeformationGradientBlend``)."""

_apply_frames = jax.jit(jax.vmap(apply, (None, 0, 0)))


def apply_frames(
    model: PoseSpaceEdit, poses: Float[ArrayLike, "T K"], posed: Float[ArrayLike, "T V 3"]
) -> Float[np.ndarray, "T V 3"]:
    """The corrected meshes of T frames (``wpse.apply`` compiled and mapped over frames)."""
    return np.asarray(_apply_frames(model, np.asarray(poses), np.asarray(posed)))


def error_summary(
    meshes: Float[ArrayLike, "T V 3"], desired: Float[ArrayLike, "T V 3"]
) -> tuple[dict[str, float], Float[np.ndarray, "T V"]]:
    """Distance of ``meshes`` to ``desired`` (centimetres in), pooled over frames and vertices.

    Returns ``{"mean_mm", "p95_mm", "max_mm"}`` and the (T, V) per-vertex errors in mm."""
    err = per_vertex_distance(meshes, desired) * CM_TO_MM
    summary = {"mean_mm": float(err.mean()), "p95_mm": float(np.percentile(err, 95))}
    return {**summary, "max_mm": float(err.max())}, err


def rest_pose_correction_mm(model: PoseSpaceEdit, rig: BlendshapeRig) -> float:
    """Largest vertex correction (mm) of ``model`` at the rest pose (all weights zero)."""
    rest = np.zeros(rig.n_blendshapes, np.float32)
    at_rest = correction(model, rest, evaluate(rig, rest))
    return float(np.linalg.norm(np.asarray(at_rest), axis=1).max() * CM_TO_MM)


@dataclasses.dataclass(frozen=True)
class MethodComparison:
    """What ``compare_methods`` measured.

    Attributes:
        errors: method -> ``"p{budget}"`` -> ``error_summary`` of the held-out frames.
        maps: method -> (H, V) per-vertex held-out errors (mm) at the last budget.
        sigma: ``"{variant}_p{budget}"`` -> the leave-one-out width (``loo_sigma``), its
            slider value (``gui_value``), ``loo_rms_mm``, the BFGS outcome and ``fit_seconds``.
        sweep: ``"{pse|wpse}_p{budget}"`` -> [(sigma, held-out mean mm)] at
            ``SWEEP_FACTORS`` times the leave-one-out width (the oracle, for reference).
        rest_correction: ``"{variant}_p{budget}"`` -> ``rest_pose_correction_mm``.
        models: (method, budget) -> the fitted model (a ``PoseSpaceEdit``, or the FSM rig).
    """

    errors: dict[str, dict[str, dict[str, float]]]
    maps: dict[str, Float[np.ndarray, "H V"]]
    sigma: dict[str, dict]
    sweep: dict[str, list[tuple[float, float]]]
    rest_correction: dict[str, float]
    models: dict[tuple[str, int], object]


def _fit_by_loo(data: EditData) -> tuple[PoseSpaceEdit, dict]:
    """The model at the leave-one-out width of ``data`` and the record of that fit."""
    start = time.perf_counter()
    fit = fit_sigma(data)
    fit_seconds = time.perf_counter() - start
    record = {
        "loo_sigma": fit.sigma,
        "gui_value": gui_from_sigma(fit.sigma),
        "loo_rms_mm": fit.loo_rms * CM_TO_MM,
        "bfgs_successful": fit.successful,
        "bfgs_steps": fit.steps,
        "fit_seconds": fit_seconds,
    }
    return fit_prepared(data, fit.sigma), record


def compare_methods(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "T K"],
    desired: Float[ArrayLike, "T V 3"],
    linear: Float[ArrayLike, "T V 3"],
    edit_frames: Int[ArrayLike, " P"],
    held_out: Int[ArrayLike, " H"],
    *,
    budgets: Sequence[int],
    sculpt: Sculpt,
    others: Mapping[str, Float[ArrayLike, "H V 3"]] | None = None,
    support_tol: float = 0.0,
) -> MethodComparison:
    """Held-out error of the linear rig, each of ``VARIANTS`` and the fix-shape method with
    the first ``budget`` edits, for each budget (the edit at frame f is desired - linear).

    Args:
        rig: the linear rig; ``linear`` is its meshes at ``poses``.
        poses: (T, K) the take's weights; desired: (T, V, 3) the meshes wanted there.
        edit_frames: frames sculpted, most problematic first; held_out: frames scored.
        budgets: numbers of edits (each <= P).
        sculpt: weights (..., K) -> the wanted meshes (..., V, 3), for the FSM's fix shapes.
        others: name -> (H, V, 3) other rigs' meshes at the held-out frames (scored too).
        support_tol: ``prepare_edits``' support tolerance (rig units).
    """
    poses, desired, linear = (np.asarray(a) for a in (poses, desired, linear))
    edit_frames, held_out = np.asarray(edit_frames), np.asarray(held_out)
    _check_budgets(budgets, edit_frames)
    others = dict(others or {})
    methods = ("linear", *VARIANTS, "fsm", *others)
    errors: dict = {m: {} for m in methods}
    maps, sigma, sweep, rest_correction, models = {}, {}, {}, {}, {}
    wanted = desired[held_out]

    def score(method, key, meshes):
        errors[method][key], maps[method] = error_summary(meshes, wanted)

    for budget in budgets:
        key = f"p{budget}"
        chosen = edit_frames[:budget]
        edits = desired[chosen] - linear[chosen]
        score("linear", key, linear[held_out])
        for name, meshes in others.items():
            score(name, key, meshes)
        for method, options in VARIANTS.items():
            data = prepare_edits(rig, poses[chosen], edits, support_tol=support_tol, **options)
            model, sigma[f"{method}_{key}"] = _fit_by_loo(data)
            models[method, budget] = model
            score(method, key, apply_frames(model, poses[held_out], linear[held_out]))
            rest_correction[f"{method}_{key}"] = rest_pose_correction_mm(model, rig)
            if method in ("pse", "wpse"):
                width = sigma[f"{method}_{key}"]["loo_sigma"]
                sweep[f"{method}_{key}"] = [
                    (
                        float(s),
                        _held_out_mean(fit_prepared(data, s), poses, linear, wanted, held_out),
                    )
                    for s in width * SWEEP_FACTORS
                ]
        fsm = fix_shape_rig(rig, coactivation_pairs(poses, budget, rig.names), sculpt)
        models["fsm", budget] = fsm
        score("fsm", key, np.asarray(evaluate_batch(fsm, poses[held_out])))
    errors = {m: errors[m] for m in methods}
    return MethodComparison(errors, maps, sigma, sweep, rest_correction, models)


def _check_budgets(budgets: Sequence[int], edit_frames: np.ndarray) -> None:
    if not budgets or not all(1 <= b <= edit_frames.size for b in budgets):
        raise ValueError(f"budgets: expected values in [1, {edit_frames.size}], got {budgets}")


def _held_out_mean(model, poses, linear, wanted, held_out) -> float:
    meshes = apply_frames(model, poses[held_out], linear[held_out])
    return error_summary(meshes, wanted)[0]["mean_mm"]


FEW_EDIT_VARIANTS = {
    "pse": ({"metric": "euclidean", "rest_pose": False}, "loo"),
    "wpse": ({"metric": "weighted", "rest_pose": False}, "loo"),
    "wpse_new_width": ({"metric": "weighted", "rest_pose": False}, "one_se"),
    "wpse_new_width_rest_pose": ({"metric": "weighted", "rest_pose": True}, "one_se"),
}
"""``few_edit_errors``' models: ``prepare_edits`` options and the width rule (``"loo"``:
``fit_sigma``, ``"one_se"``: the one-standard-error width of ``fit_width``)."""


def _one_se_width(data: EditData, edits: np.ndarray) -> tuple[float, dict]:
    start = time.perf_counter()
    fit = fit_width(data)
    record = {
        "sigma": fit.sigma,
        "loo_min_sigma": fit.loo_min_sigma,
        "standard_error_mm": fit.standard_error * CM_TO_MM,
        "loo_mean_at_sigma_mm": float(
            fit.loo_mean[np.searchsorted(fit.grid, fit.sigma)] * CM_TO_MM
        ),
        "loo_mean_at_min_mm": float(fit.loo_mean.min() * CM_TO_MM),
        "no_correction_mm": float(np.linalg.norm(edits, axis=2).mean() * CM_TO_MM),
        "fit_seconds": time.perf_counter() - start,
    }
    return fit.sigma, record


def few_edit_errors(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "T K"],
    desired: Float[ArrayLike, "T V 3"],
    linear: Float[ArrayLike, "T V 3"],
    edit_frames: Int[ArrayLike, " P"],
    held_out: Int[ArrayLike, " H"],
    *,
    budgets: Sequence[int],
    known_sigma: Mapping[str, float] | None = None,
    support_tol: float = 0.0,
) -> tuple[dict[str, dict], dict[str, dict]]:
    """Held-out error with few edits: the leave-one-out width against the one-standard-error
    width (``fit_width``), chosen from the edits alone, for each of ``FEW_EDIT_VARIANTS``.

    Arguments as for ``compare_methods``; ``known_sigma`` maps ``"{pse|wpse}_p{budget}"`` to
    a leave-one-out width already fitted to the same edits (else it is fitted here).

    Returns ``rows``: ``str(budget)`` -> method (``"linear"`` first) -> held-out mean and
    p95 (mm) and, for the edit models, the width used; ``widths``:
    ``"{variant}_p{budget}"`` -> the one-standard-error fit (sigma, its LOO minimum, the
    standard error and LOO means in mm, the mean edit size ``no_correction_mm``, seconds).
    """
    poses, desired, linear = (np.asarray(a) for a in (poses, desired, linear))
    edit_frames, held_out = np.asarray(edit_frames), np.asarray(held_out)
    _check_budgets(budgets, edit_frames)
    wanted = desired[held_out]
    known_sigma = dict(known_sigma or {})

    def mean_p95(meshes):
        summary = error_summary(meshes, wanted)[0]
        return {"mean_mm": summary["mean_mm"], "p95_mm": summary["p95_mm"]}

    rows, widths = {}, {}
    for budget in budgets:
        chosen = edit_frames[:budget]
        edits = desired[chosen] - linear[chosen]
        row = {"linear": mean_p95(linear[held_out])}
        for method, (options, rule) in FEW_EDIT_VARIANTS.items():
            data = prepare_edits(rig, poses[chosen], edits, support_tol=support_tol, **options)
            key = f"{method}_p{budget}"
            if rule == "loo":
                width = known_sigma[key] if key in known_sigma else fit_sigma(data).sigma
            else:
                width, widths[key] = _one_se_width(data, edits)
            model = fit_prepared(data, width)
            meshes = apply_frames(model, poses[held_out], linear[held_out])
            row[method] = {**mean_p95(meshes), "sigma": width}
        rows[str(budget)] = row
    return rows, widths


def temporal_smoothness(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "T K"],
    desired: Float[ArrayLike, "T V 3"],
    linear: Float[ArrayLike, "T V 3"],
    edit_frames: Int[ArrayLike, " P"],
    take: Int[ArrayLike, " N"],
    *,
    sigma: float,
    support_tol: float = 0.0,
) -> tuple[dict, dict[str, Float[np.ndarray, " _"]]]:
    """One edit at the worst frame of ``take`` not among ``edit_frames``, applied over the
    whole take (Seol et al.'s Figure 6: an edit should change smoothly over time).

    Args:
        take: (N,) consecutive frames of a take (indices into ``poses``).
        sigma: the edit's width. Others as for ``compare_methods``.

    Returns the summary (``edited_frame``; the correction's ``max_step_mm`` (mm/frame) and
    ``max_acceleration_mm`` (mm/frame^2), the same of the wanted meshes themselves
    (``take_*``), the largest correction ``max_correction_mm``) and the curves: ``size`` (N,)
    the largest vertex correction of each frame (mm), ``step`` and ``take_step`` (N-1,) the
    largest vertex step of the correction and of the take (mm/frame).
    """
    poses, desired, linear = (np.asarray(a) for a in (poses, desired, linear))
    take = np.asarray(take)
    candidates = np.setdiff1d(take, edit_frames)
    if candidates.size == 0:
        raise ValueError("take: every frame of the take is an edit frame")
    error = np.linalg.norm(desired[candidates] - linear[candidates], axis=2).mean(axis=1)
    frame = int(candidates[np.argmax(error)])
    model = fit_pose_space_edit(
        rig,
        poses[frame][None],
        (desired[frame] - linear[frame])[None],
        sigma=sigma,
        support_tol=support_tol,
    )
    corrected = apply_frames(model, poses[take], linear[take])
    correction_mm = (corrected - linear[take]) * CM_TO_MM
    change = temporal_change(correction_mm)
    motion = temporal_change(desired[take] * CM_TO_MM)
    size = np.linalg.norm(correction_mm, axis=2).max(axis=1)
    summary = {
        "edited_frame": frame,
        "sigma": sigma,
        "max_step_mm": change["max_step"],
        "max_acceleration_mm": change["max_acceleration"],
        "take_max_step_mm": motion["max_step"],
        "take_max_acceleration_mm": motion["max_acceleration"],
        "max_correction_mm": float(size.max()),
        "frames": int(take.size),
    }
    curves = {"size": size, "step": change["step"], "take_step": motion["step"]}
    return summary, {k: np.asarray(v) for k, v in curves.items()}


def channel_region(
    rig: BlendshapeRig, channels: Channels, threshold: float = 0.5
) -> Int[np.ndarray, " R"]:
    """Vertices that ``channels`` move: where their summed ``blendshape_metric`` weight
    (each vertex's weights sum to 1 over all blendshapes) exceeds ``threshold``."""
    alpha = blendshape_metric(rig.deltas)
    return np.flatnonzero(alpha[:, np.asarray(channels, np.int64)].sum(axis=1) > threshold)


def reuse_by_search(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "T K"],
    desired: Float[ArrayLike, "T V 3"],
    linear: Float[ArrayLike, "T V 3"],
    take: Int[ArrayLike, " N"],
    *,
    region_channels: Channels,
    library_size: int,
    min_distance: float,
    support_tol: float = 0.0,
    tau_scales: Sequence[float] = (1.0, 0.5, 1.5),
) -> dict:
    """Edit reuse (eq. 7): a library of edits at the worst spread-out frames of the first half
    of ``take`` corrects the second half through the search over the region that
    ``region_channels`` move (``channel_region``).

    E / |ROI| is the mean weighted pose distance over the region, so tau is set from the
    library's one-standard-error width alone: tau = 2 sigma |ROI| (edits whose Gaussian still
    weighs about e^-2 over the region); also at the other ``tau_scales`` (the first is 1).

    Returns the library and query frames, the ROI size, the width, the second half's mean
    error (mm) before, and for each scale the error after, the frames where edits were found
    and their mean number (scale 1 at the top level, scale s under ``"tau_x{s:g}"``).
    """
    poses, desired, linear = (np.asarray(a) for a in (poses, desired, linear))
    take = np.asarray(take)
    half = take.size // 2
    first, second = take[:half], take[half:]
    error = np.linalg.norm(desired[first] - linear[first], axis=2).mean(axis=1)
    library = first[select_edit_frames(error, poses[first], library_size, min_distance)]
    edits = desired[library] - linear[library]
    roi = channel_region(rig, region_channels)
    data = prepare_edits(rig, poses[library], edits, support_tol=support_tol)
    width = fit_width(data).sigma
    tau = 2.0 * width * roi.size
    before = per_vertex_distance(linear[second], desired[second]) * CM_TO_MM
    out = {
        "library_frames": library.tolist(),
        "query_frames": [int(second[0]), int(second[-1])],
        "roi_vertices": int(roi.size),
        "sigma": width,
        "error_before_mm": float(before.mean()),
        "error_before_roi_mm": float(before[:, roi].mean()),
    }
    for scale in tau_scales:
        found = reuse_edits(
            rig,
            poses[library],
            edits,
            poses[second],
            roi,
            tau=scale * tau,
            sigma=width,
            support_tol=support_tol,
        )
        after = per_vertex_distance(linear[second] + found.corrections, desired[second])
        after = after * CM_TO_MM
        row = {
            "tau": scale * tau,
            "tau_per_roi_vertex": scale * tau / roi.size,
            "error_after_mm": float(after.mean()),
            "error_after_roi_mm": float(after[:, roi].mean()),
            "frames_with_edits_found": int(sum(f.size > 0 for f in found.found)),
            "mean_edits_found": float(np.mean([f.size for f in found.found])),
        }
        if scale == 1.0:
            out.update(row)
        else:
            out[f"tau_x{scale:g}"] = row
    return out
