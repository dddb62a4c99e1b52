"""Probes of a fitted edit model away from the held-out frames (Seol et al.'s Figures 7, 9
and 10 and the search of section 4): how local a correction stays when other channels move,
how far it overshoots past a sculpted corner, how two nearby sculpts combine, and which
stored edits a region's search ranks first.

Meshes are in the rig's units (ICT: centimetres); sizes are reported in millimetres.
``sculpt`` is the mesh the artist wants: a callable weights (..., K) -> meshes (..., V, 3)
(e.g. ``mesh.DeformationGradientBlend``).
"""

from collections.abc import Mapping
from typing import Any

import jax
import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ..._metrics import CM_TO_MM, per_vertex_distance
from ...rig import BlendshapeRig, evaluate_batch
from ...wpse._layers import apply_layered, fit_layered
from ...wpse._metric import blendshape_metric
from ...wpse._pse import PoseSpaceEdit, apply, fit_pose_space_edit
from ...wpse._search import search_edits
from ._protocol import retained_fraction
from ._protocols import Channels, Sculpt, channel_region

_apply_each = jax.vmap(apply, (None, 0, 0))


def locality_probe(
    rig: BlendshapeRig,
    models: Mapping[str, PoseSpaceEdit],
    poses: Float[ArrayLike, "T K"],
    edit_frames: Int[ArrayLike, " P"],
    linear: Float[ArrayLike, "T V 3"],
    sculpt: Sculpt,
    rng: np.random.Generator,
    *,
    eye_channels: Channels,
    mouth_channels: Channels,
    draws: int = 4,
    min_correction_mm: float = 1.0,
) -> dict:
    """Figure 7: at each edited pose, the eye weights redrawn uniformly in [0, 1] (``draws``
    probes); how much of the mouth correction each model keeps (``retained_fraction`` over
    the vertices the mouth channels move, 1: all of it), and the wanted mesh itself.

    Edits whose wanted mouth correction stays under ``min_correction_mm`` are skipped (their
    draws are still taken from ``rng``, so the probes do not depend on the threshold).

    Returns ``"{name}_retained"`` (mean over probes) for each model and ``desired_retained``,
    the number of ``probes`` per model, ``region_vertices`` and ``eye_channels``.
    """
    if draws < 1:
        raise ValueError(f"draws: expected >= 1, got {draws}")
    poses, linear = np.asarray(poses), np.asarray(linear)
    eye = np.asarray(eye_channels, np.int64)
    region = channel_region(rig, mouth_channels)
    out = {name: [] for name in (*models, "desired")}
    for frame in np.asarray(edit_frames):
        edit_pose = poses[frame]
        probes = np.repeat(edit_pose[None], draws, axis=0)
        probes[:, eye] = rng.uniform(0.0, 1.0, (draws, eye.size))
        probe_linear = np.asarray(evaluate_batch(rig, probes))
        desired_probe = sculpt(probes) - probe_linear
        desired_edit = sculpt(edit_pose) - linear[frame]
        if np.linalg.norm(desired_edit[region], axis=1).max() * CM_TO_MM < min_correction_mm:
            continue
        for name, model in models.items():
            at_edit = np.asarray(apply(model, edit_pose, linear[frame])) - linear[frame]
            at_probe = np.asarray(_apply_each(model, probes, probe_linear)) - probe_linear
            out[name] += [retained_fraction(at_edit, c, region) for c in at_probe]
        out["desired"] += [retained_fraction(desired_edit, c, region) for c in desired_probe]
    if not out["desired"]:
        raise ValueError(f"edit_frames: no edit corrects the mouth by {min_correction_mm} mm")
    return {
        **{f"{name}_retained": float(np.mean(v)) for name, v in out.items()},
        "probes": len(out["desired"]),
        "region_vertices": int(region.size),
        "eye_channels": int(eye.size),
    }


def overshoot_sweep(
    rig: BlendshapeRig,
    fsm: BlendshapeRig,
    models: Mapping[str, PoseSpaceEdit],
    sculpt: Sculpt,
    *,
    sigma: float,
    t: Float[ArrayLike, " N"] | None = None,
) -> tuple[dict, dict[str, Float[np.ndarray, " N"]]]:
    """Figure 9: the pair of channels with the largest fix shape of ``fsm`` swept together
    along ``t`` (both weights t, the others 0); the largest vertex correction (mm) of the
    wanted mesh (``desired``), the FSM, a WPSE model of the one edit at t = 1
    (``wpse_corner_edit``, width ``sigma``) and each of ``models``. ``t`` defaults to
    0, 0.05, ..., 1.5.

    Returns ``{"pair": [two names], "max_correction_mm": curve -> {"t=x": mm}}`` at t = 0,
    0.5, 1 and 1.5 (each must be in ``t``), and each curve (N,) in mm.
    """
    t = np.linspace(0.0, 1.5, 31) if t is None else np.asarray(t, np.float64)
    shown = (0.0, 0.5, 1.0, 1.5)
    if t.ndim != 1 or not all(np.any(t == x) for x in shown):
        raise ValueError(f"t: expected a 1-D sweep containing {shown}")
    table = fsm.corrective(2)
    if table is None:
        raise ValueError("fsm: expected a rig with fix shapes of channel pairs, got none")
    largest = int(np.argmax(np.linalg.norm(np.asarray(table.deltas), axis=2).max(axis=1)))
    pair = np.asarray(table.indices[largest])
    sweep = np.zeros((t.size, rig.n_blendshapes), np.float32)
    sweep[:, pair] = t[:, None]
    base = np.asarray(evaluate_batch(rig, sweep))
    corner = int(np.argmin(np.abs(t - 1.0)))
    corner_edit = sculpt(sweep[corner])[None] - base[corner][None]
    single = fit_pose_space_edit(rig, sweep[corner][None], corner_edit, sigma=sigma)
    curves = {
        "desired": sculpt(sweep) - base,
        "fsm": np.asarray(evaluate_batch(fsm, sweep)) - base,
        "wpse_corner_edit": np.asarray(_apply_each(single, sweep, base)) - base,
        **{k: np.asarray(_apply_each(m, sweep, base)) - base for k, m in models.items()},
    }
    magnitude = {k: np.linalg.norm(v, axis=2).max(axis=1) * CM_TO_MM for k, v in curves.items()}
    at = {float(x): int(i) for i, x in enumerate(t)}
    summary = {
        "pair": [rig.names[i] for i in pair],
        "max_correction_mm": {
            k: {f"t={x}": float(v[at[x]]) for x in shown} for k, v in magnitude.items()
        },
    }
    return summary, magnitude


def layering_probe(
    rig: BlendshapeRig,
    pose: Float[ArrayLike, " K"],
    sculpt: Sculpt,
    *,
    sigma: float,
    step: float = 0.05,
    exaggerate: float = 1.5,
    eta: float = 0.1,
    layer_sigma: float | None = None,
) -> dict:
    """Figure 10: two different sculpts at nearly the same pose, one layer against layers.

    Pose a is ``pose``; pose b adds ``step`` to its largest weight. Edit a is the wanted
    correction at a, edit b ``exaggerate`` times the one at b. One model of width ``sigma``
    against ``fit_layered`` (``eta``; layer width ``layer_sigma``, default ``sigma / 10``).

    Returns, per model (``single_layer``, ``layered``), the largest vertex error (mm) at
    each edit, between them (against the two sculpts blended linearly along the segment) and
    the largest correction on the line through both (4 segments before a to 4 after b);
    ``largest_sculpt_mm`` and ``n_layers``.
    """
    a = np.asarray(pose).copy()
    b = a.copy()
    b[int(np.argmax(a))] += step
    two = np.stack([a, b])
    base = np.asarray(evaluate_batch(rig, two))
    fix = sculpt(two) - base
    edits = np.stack([fix[0], exaggerate * fix[1]])
    between = np.linspace(0.0, 1.0, 11)[:, None] * (b - a)[None] + a[None]
    beyond = np.linspace(-4.0, 5.0, 37)[:, None] * (b - a)[None] + a[None]
    base_between = np.asarray(evaluate_batch(rig, between))
    base_beyond = np.asarray(evaluate_batch(rig, beyond))
    target_between = base_between + (
        np.linspace(0.0, 1.0, 11)[:, None, None] * (edits[1] - edits[0])[None] + edits[0][None]
    )
    layer_sigma = sigma / 10 if layer_sigma is None else layer_sigma
    models = {
        "single_layer": (fit_pose_space_edit(rig, two, edits, sigma=sigma), _apply_each),
        "layered": (
            fit_layered(rig, two, edits, sigma=sigma, eta=eta, layer_sigma=layer_sigma),
            jax.vmap(apply_layered, (None, 0, 0)),
        ),
    }
    out: dict[str, Any] = {"pose_distance": float(np.linalg.norm(b - a)), "sigma": sigma}
    out["layer_sigma"] = layer_sigma
    for name, (model, run) in models.items():
        err = per_vertex_distance(np.asarray(run(model, two, base)), base + edits) * CM_TO_MM
        mid = np.asarray(run(model, between, base_between))
        far = np.asarray(run(model, beyond, base_beyond)) - base_beyond
        err_between = per_vertex_distance(mid, target_between) * CM_TO_MM
        out[name] = {
            "edit_a_max_mm": float(err[0].max()),
            "edit_b_max_mm": float(err[1].max()),
            "between_max_mm": float(err_between.max()),
            "max_correction_on_line_mm": float(np.linalg.norm(far, axis=2).max() * CM_TO_MM),
        }
    out["largest_sculpt_mm"] = float(np.linalg.norm(edits, axis=2).max() * CM_TO_MM)
    out["n_layers"] = models["layered"][0].n_layers
    return out


def search_by_region(
    rig: BlendshapeRig,
    library: Float[ArrayLike, "N K"],
    query: Float[ArrayLike, " K"],
    regions: Mapping[str, Channels],
    *,
    percentile: float = 20.0,
) -> dict[str, dict]:
    """Section 4: rank the stored edit poses ``library`` for one ``query`` pose by each
    region (name -> the channels that move it, ``channel_region``).

    tau is the ``percentile`` of the region energies E over the library. Returns, per
    region, ``roi`` (R,) its vertices, ``tau`` and ``found`` (``search_edits``'s result:
    library indices with E < tau, lowest E first)."""
    alpha = blendshape_metric(rig.deltas)
    library, query = np.asarray(library), np.asarray(query)
    out = {}
    for name, channels in regions.items():
        roi = channel_region(rig, channels)
        energy = search_edits(alpha, library, query, roi).energies
        tau = float(np.percentile(energy, percentile))
        out[name] = {"roi": roi, "tau": tau, "found": search_edits(alpha, library, query, roi, tau)}
    return out
