"""Evaluation protocols of the CANRig workflows on the ict-quartic rig: the paper's Table 4
(pose A to B, direct and fitted) with the floor no result can beat, Figure 15 (iterative
layers), Figure 10 (clip editing), Figure 12 / Table 6 (dialogue replacement with the
global-blendshape baselines), and the selection of the rig with no network beside them
(``LocalFitRig``, beyond the paper).

The experiment scripts (``experiments/canrig_workflows.py``, ``canrig_workflows_floor.py``,
``canrig_workflows_dialogue.py``) call these; the tests call them here. Shapes and distances
in cm (the rig's units), errors in mm.
"""

import dataclasses
import json
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Float32, Int

from ..._metrics import CM_TO_MM
from ...canrig._data import EVAL_FALLOFF_PER_CM, RADII_CM, evaluate_poses
from ...canrig._handle_rig import FitOptions, Handles
from ...canrig._layout import influence_reach
from ...canrig._masks import influence_mask
from ...canrig._rig import NeuralRig
from ...canrig._train import load_model
from ...canrig._workflows import (
    ClipEdit,
    clip_edit,
    dialogue_replacement,
    expression_region,
    interior_vertices,
    iterative_layers,
    max_acceleration,
    pose_a_to_b,
)
from ...data import load_livelinkface
from ...mesh import farthest_point_vertices
from ...pbs._basis import global_blendshape_dialogue, patch_layout, pbs_basis
from ...pbs._local_fit import local_fit_rig
from ...rig import BlendshapeRig, ict_quartic_rig, random_sparse_poses
from ._splits import held_out_poses, split_capture

FALLOFF_PER_CM = EVAL_FALLOFF_PER_CM
"""Falloff of every workflow's masks (per cm), as CANRig's evaluation."""
HANDLE_COUNTS = (20, 75, 200)
"""Table 4's handle counts."""
LAYER_SCHEDULE = ((20, 4.0), (75, 2.0), (200, 1.0))
"""Figure 15's layers: (random handles, radius in cm), coarse to fine."""
DISTANCE_LIMIT_CM = 5.0
"""Geodesic distances are computed up to this limit: beyond the reach of a 4 cm mask at
falloff 3/cm (4.77 cm), so every mask is exact."""
CLIP_HANDLES, CLIP_HALF_WINDOW, CLIP_RADIUS_CM = 12, 10, 3.0
"""Figure 10's clip edit: handles on the mouth and chin, frames faded on each side, radius."""
DIALOGUE_HANDLES, DIALOGUE_RADIUS_CM = 60, 1.5
"""Figure 12's dialogue replacement: handles inside the mouth mask, their radius (cm)."""
DIALOGUE_SOURCE_FRAME, DIALOGUE_TARGET_FRAME = 90, 135
"""First capture frames of the dialogue's source and target clips."""
MOUTH_THRESHOLD_CM = 0.3
"""The mouth mask: what jaw*/mouth* expressions move more than this and eye*/brow* do not."""
LOCAL_FIT_GRID = {"patches": (300, 600), "basis": (19, 40, 60), "ridge": (1e-4, 1e-3, 1e-2)}
"""The ``LocalFitRig`` configurations ``select_local_fit`` compares."""
LOCAL_FIT_DESCRIPTION = (
    "canrig.LocalFitRig (no network): per patch a ridge fit of the basis offsets "
    "to the handle displacements its clamped masks see (at the patch seed), blended by the "
    "layout, each vertex scaled by min(1, 2 x its largest clamped mask); basis: pbs_basis "
    "(farthest points in shape space) of the network's training shapes; fitted: "
    "FitOptions.max_steps "
    "LSMR iterations from the direct displacements"
)


def _error_mm(a, b) -> np.ndarray:
    """(..., V) per-vertex distance (mm) of two (..., V, 3) shapes in cm, in their dtype."""
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1) * CM_TO_MM


# --------------------------------------------------------------------------- data and rigs


@dataclasses.dataclass(frozen=True)
class WorkflowData:
    """The ict-quartic rig, the Live Link capture on its channels (F, K), the capture's
    held-out half (its second, F/2 frames) and the held-out shapes (S, V, 3) in cm: that
    half and 100 random sparse poses (``held_out_poses``, as ``canrig_eval.py``)."""

    quartic: BlendshapeRig
    capture: Float32[np.ndarray, "F K"]
    capture_test: Float32[np.ndarray, "F_test K"]
    shapes: Float32[np.ndarray, "S V 3"]


def workflow_data(data_dir: str | Path | None = None) -> WorkflowData:
    """Load ``WorkflowData`` from the data folder (``None``: ``$CANRIG_DATA``)."""
    quartic, _ = ict_quartic_rig(data_dir, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(data_dir).weights_for(quartic.names, missing="zero")
    _, capture_test = split_capture(capture)
    poses = held_out_poses(capture_test, quartic.names, n_random=100)
    return WorkflowData(quartic, capture, capture_test, evaluate_poses(quartic, poses))


def network_rig(checkpoint: str | Path, quartic: BlendshapeRig) -> tuple[NeuralRig, dict]:
    """The trained CANRig of ``checkpoint`` on the rig's mesh, and the protocol's model entry
    (checkpoint, training steps and minutes, its handle-set and radius sampling)."""
    neutral = np.asarray(quartic.neutral, np.float32)
    model, state = load_model(checkpoint, neutral)
    rig = NeuralRig(model, neutral, np.asarray(quartic.faces))
    return rig, {
        "checkpoint": str(checkpoint),
        "train_steps": state["step"],
        "train_minutes": state["seconds"] / 60.0,
        "p_farthest": state["options"]["examples"]["p_farthest"],
        "p_eval_radius": state["options"]["examples"]["p_eval_radius"],
    }


def local_fit_training_shapes(
    quartic: BlendshapeRig, capture: Float[np.ndarray, "F K"]
) -> Float32[np.ndarray, "T V 3"]:
    """(T, V, 3) the network's training shapes (``build_training_set``'s poses, seed 0): the
    capture's first half and 800 random sparse poses; never a held-out pose."""
    capture_train, _ = split_capture(capture)
    train = np.concatenate(
        [
            capture_train,
            random_sparse_poses(np.random.default_rng(0), 800, quartic.names, n_active=(4, 10)),
        ]
    ).astype(np.float32)
    return np.asarray(evaluate_poses(quartic, train))


def random_pairs(n_poses: int, n_pairs: int, rng: np.random.Generator) -> Int[np.ndarray, "n 2"]:
    """(n_pairs, 2) random (A, B) pose indices below ``n_poses``, A != B in every pair."""
    if n_poses < 2:
        raise ValueError(f"n_poses: expected >= 2 to draw A != B, got {n_poses}")
    a = rng.integers(0, n_poses, n_pairs)
    b = (a + rng.integers(1, n_poses, n_pairs)) % n_poses
    return np.stack([a, b], axis=1)


def select_local_fit(
    quartic: BlendshapeRig,
    capture: Float[np.ndarray, "F K"],
    *,
    seed: int = 0,
    n_pairs: int = 30,
    progress: Callable[[str], object] = print,
) -> tuple[NeuralRig, dict]:
    """The ``LocalFitRig`` whose patch count, basis size and ridge (``LOCAL_FIT_GRID``) give
    the lowest direct A-to-B error at 200 random handles / 2 cm on ``n_pairs`` pairs of the
    network's *training* shapes (``local_fit_training_shapes``); its basis is ``pbs_basis``
    of those shapes. Returns (the rig, the protocol's model entry with the whole selection:
    each configuration's mean error in mm)."""
    train_shapes = local_fit_training_shapes(quartic, capture)
    neutral, faces = np.asarray(quartic.neutral, np.float32), np.asarray(quartic.faces)
    rng = np.random.default_rng([seed, 7])
    select_pairs = random_pairs(len(train_shapes), n_pairs, rng)
    select_sets = [rng.choice(len(neutral), 200, replace=False) for _ in select_pairs]
    selection, best, handles = [], None, None
    for n_patches in LOCAL_FIT_GRID["patches"]:
        layout = patch_layout(neutral, faces, n_patches, rings=3)
        for n_basis in LOCAL_FIT_GRID["basis"]:
            basis, _ = pbs_basis(neutral, train_shapes, n_basis)
            for ridge in LOCAL_FIT_GRID["ridge"]:
                rig = NeuralRig(local_fit_rig(layout, basis, ridge), neutral, faces)
                if handles is None:  # the same placements (geodesic distances) for every rig
                    handles = [rig.handles(h, limit=DISTANCE_LIMIT_CM) for h in select_sets]
                errors = [
                    pose_a_to_b(rig, h, train_shapes[a], train_shapes[b], 2.0, FALLOFF_PER_CM).error
                    for (a, b), h in zip(select_pairs, handles, strict=True)
                ]
                row = {
                    "patches": n_patches,
                    "basis": n_basis,
                    "ridge": ridge,
                    "mm": float(np.mean(errors)) * CM_TO_MM,
                }
                selection.append(row)
                progress(f"  selection on training pairs: {row}")
                if best is None or row["mm"] < best[0]["mm"]:
                    best = (row, rig)
    assert best is not None  # LOCAL_FIT_GRID has at least one configuration
    chosen, rig = best
    protocol = {
        "rig": LOCAL_FIT_DESCRIPTION,
        "selected": chosen,
        "selection_on_training_pairs": selection,
    }
    return rig, protocol


def local_fit_from_selection(
    quartic: BlendshapeRig, capture: Float[np.ndarray, "F K"], selected: Mapping
) -> NeuralRig:
    """The ``LocalFitRig`` that ``select_local_fit`` chose (``selected``: its protocol entry's
    ``"selected"``, with ``patches``, ``basis`` and ``ridge``), rebuilt without the search."""
    missing = {"patches", "basis", "ridge"} - set(selected)
    if missing:
        raise ValueError(f"selected: expected patches, basis and ridge, missing {sorted(missing)}")
    train_shapes = local_fit_training_shapes(quartic, capture)
    neutral, faces = np.asarray(quartic.neutral, np.float32), np.asarray(quartic.faces)
    layout = patch_layout(neutral, faces, int(selected["patches"]), rings=3)
    basis, _ = pbs_basis(neutral, train_shapes, int(selected["basis"]))
    return NeuralRig(local_fit_rig(layout, basis, float(selected["ridge"])), neutral, faces)


def results_of_the_same_pairs(path: str | Path, pairs: int, seed: int, flag: str) -> dict:
    """The results.json at ``path``, checked to hold Table 4 with these ``pairs`` and
    ``seed`` (a ``ValueError`` naming ``flag`` otherwise; a file from before the seed was
    recorded has seed 0)."""
    results = json.loads(Path(path).read_text())
    protocol = results["protocol"]
    if (protocol["pairs"], protocol.get("seed", 0)) != (pairs, seed):
        raise ValueError(
            f"{flag}: pass the --pairs and --seed of {path} "
            f"({protocol['pairs']}, {protocol.get('seed', 0)}; the seed was 0 before it was "
            "recorded)"
        )
    return results


# --------------------------------------------------------------------------- Table 4


def table4_protocol(
    n_shapes: int, n_vertices: int, n_pairs: int, seed: int
) -> tuple[Int[np.ndarray, "n 2"], dict[int, list[Int[np.ndarray, " _"]]], np.random.Generator]:
    """Table 4's random protocol: (n_pairs, 2) (A, B) pairs of shape indices, per handle
    count of ``HANDLE_COUNTS`` one random set of distinct vertices per pair, and the handle
    generator in the state the rest of the experiment continues from (the layers draw
    from it)."""
    pairs = random_pairs(n_shapes, n_pairs, np.random.default_rng(seed))
    handle_rng = np.random.default_rng([seed, 1])
    random_sets = {
        n: [handle_rng.choice(n_vertices, n, replace=False) for _ in range(n_pairs)]
        for n in HANDLE_COUNTS
    }
    return pairs, random_sets, handle_rng


def unreached_floor(
    rig: NeuralRig,
    shapes: Float[np.ndarray, "S V 3"],
    pairs: Int[np.ndarray, "n 2"],
    random_sets: Mapping[int, list],
    progress: Callable[[str], object] = print,
) -> dict:
    """{handles: {radius name: {floor_mm, unreached_percent}}}: a lower bound of any A-to-B
    result under Table 4's random-vertex protocol. A vertex beyond every handle's reach
    (``influence_reach``: its clamped masks are exactly 0) keeps A's position whatever the
    network or the fit, so its error |A - B| is in every result; the floor is that error
    averaged over all vertices (0 on reached ones), then over the pairs (mm)."""
    table = {}
    for n in random_sets:
        floors = {name: [] for name in RADII_CM}
        unreached = {name: [] for name in RADII_CM}
        for p, (a, b) in enumerate(pairs):
            nearest = np.asarray(
                rig.handles(random_sets[n][p], limit=DISTANCE_LIMIT_CM).distance
            ).min(axis=1)
            error = _error_mm(shapes[a], shapes[b])
            for name, radius in RADII_CM.items():
                reach = float(influence_reach(radius, FALLOFF_PER_CM, rig.model.clamp))
                still = nearest > reach
                floors[name].append(float(np.where(still, error, 0.0).mean()))
                unreached[name].append(float(still.mean()))
        table[str(n)] = {
            name: {
                "floor_mm": float(np.mean(floors[name])),
                "unreached_percent": 100 * float(np.mean(unreached[name])),
            }
            for name in RADII_CM
        }
        progress(f"  floor, {n} handles: {table[str(n)]}")
    return table


def a_to_b_cell(
    direct: Sequence[float] | Float[ArrayLike, " n"],
    fitted: Sequence[float] | Float[ArrayLike, " m"],
    fitted_vertices: Sequence[Float[ArrayLike, " V"]],
    own_direct: Sequence[float] | Float[ArrayLike, " m"],
) -> dict:
    """One Table 4 cell from per-pair mean errors (mm; the first pairs fitted too), the
    fitted pairs' per-vertex errors (each (V,), mm) and each fit's own direct error
    (``FitSolution``'s ``direct_error``, its start evaluated inside the fit's compiled
    program, mm).

    ``fitted_never_worse`` is the library's guarantee, fitted <= its own direct error
    (exact); against the separate direct pass the two compiled programs round differently,
    so the largest excess over it is reported beside (float32 rounding, ~1e-6 mm)."""
    direct = np.asarray(direct, np.float64)
    fitted = np.asarray(fitted, np.float64)
    n_fitted = len(fitted)
    if n_fitted == 0 or n_fitted > len(direct) or len(fitted_vertices) != n_fitted:
        raise ValueError(
            f"fitted: expected 1..{len(direct)} pairs with their per-vertex errors, got "
            f"{n_fitted} and {len(fitted_vertices)}"
        )
    return {
        "direct_mm": float(direct.mean()),
        "fitted_mm": float(fitted.mean()),
        "fitted_p95_mm": float(np.percentile(np.concatenate(fitted_vertices), 95)),
        "direct_on_fitted_pairs_mm": float(direct[:n_fitted].mean()),
        "fitted_never_worse": bool(np.all(fitted <= np.asarray(own_direct))),
        "fitted_excess_over_direct_pass_max_mm": float(
            np.max(fitted - direct[:n_fitted], initial=0.0)
        ),
        "pairs_direct": len(direct),
        "pairs_fitted": n_fitted,
    }


def a_to_b_table(
    rig: NeuralRig,
    shapes: Float[np.ndarray, "S V 3"],
    pairs: Int[np.ndarray, "n 2"],
    placements: Callable[[int, int], Handles],
    n_fit: int,
    options: FitOptions,
    progress: Callable[[str], object] = print,
    n_fit_main: int = 0,
    handle_counts: tuple[int, ...] = HANDLE_COUNTS,
    radii_cm: Mapping[str, float] = RADII_CM,
) -> dict:
    """{handles: {radius name: ``a_to_b_cell``}} for one handle placement protocol
    (``placements(pair index, handle count) -> Handles``): every pair direct, the first
    ``n_fit`` fitted too (``n_fit_main`` at 200 handles / the medium radius, the issue's
    target cell, when larger)."""
    table = {}
    for n in handle_counts:
        table[str(n)] = {}
        cells = {
            name: {"direct": [], "fitted": [], "fitted_vertices": [], "own_direct": []}
            for name in radii_cm
        }
        for p, (a, b) in enumerate(pairs):
            handles = placements(p, n)
            for name, radius in radii_cm.items():
                direct = pose_a_to_b(rig, handles, shapes[a], shapes[b], radius, FALLOFF_PER_CM)
                cells[name]["direct"].append(float(direct.error) * CM_TO_MM)
                main_cell = n == 200 and name == "medium"
                if p < (max(n_fit, n_fit_main) if main_cell else n_fit):
                    fitted = pose_a_to_b(
                        rig,
                        handles,
                        shapes[a],
                        shapes[b],
                        radius,
                        FALLOFF_PER_CM,
                        fit=True,
                        options=options,
                    )
                    cells[name]["fitted"].append(float(fitted.error) * CM_TO_MM)
                    cells[name]["own_direct"].append(float(fitted.direct_error) * CM_TO_MM)
                    cells[name]["fitted_vertices"].append(_error_mm(fitted.shape, shapes[b]))
            if (p + 1) % 100 == 0:
                progress(f"  {n} handles: {p + 1}/{len(pairs)} pairs")
        for name, cell in cells.items():
            table[str(n)][name] = a_to_b_cell(**cell)
        progress(
            f"  {n} handles: "
            + ", ".join(
                f"{k} {v['direct_mm']:.3f} -> {v['fitted_mm']:.3f} mm"
                for k, v in table[str(n)].items()
            )
        )
    return table


# --------------------------------------------------------------------------- layers, clip


def layers_protocol(
    rig: NeuralRig,
    shapes: Float[np.ndarray, "S V 3"],
    pairs: Int[np.ndarray, "n 2"],
    handle_rng: np.random.Generator,
    options: FitOptions,
) -> tuple[dict, dict[str, Float[np.ndarray, "n L"]]]:
    """Figure 15: per pair, ``iterative_layers`` from A towards B over ``LAYER_SCHEDULE``
    (new random handles per layer from ``handle_rng``), direct and fitted. Returns the
    summary (each kind's mean error after each layer, mm; whether the fitted errors never
    rise on any pair) and each kind's (n, layers) errors (mm)."""
    errors = {"direct": [], "fitted": []}
    for a, b in pairs:
        schedule = [
            (rig.handles(handle_rng.choice(rig.n_vertices, n, replace=False)), radius)
            for n, radius in LAYER_SCHEDULE
        ]
        for kind in errors:
            result = iterative_layers(
                rig,
                shapes[a],
                shapes[b],
                schedule,
                FALLOFF_PER_CM,
                fit=kind == "fitted",
                options=options,
            )
            errors[kind].append(result.errors * CM_TO_MM)
    layers = {f"{k}_mm": np.mean(v, axis=0).tolist() for k, v in errors.items()}
    fitted = np.array(errors["fitted"])
    layers["fitted_non_increasing_every_pair"] = bool(np.all(np.diff(fitted, axis=1) <= 0))
    layers["pairs"] = len(fitted)
    return layers, {k: np.array(v) for k, v in errors.items()}


@dataclasses.dataclass(frozen=True)
class ClipEditRun:
    """``clip_edit_protocol``'s clip (F, V, 3), its edit, the edited frame and the target
    shape at that frame (V, 3), all in cm."""

    clip: Float32[np.ndarray, "F V 3"]
    edited: ClipEdit
    frame: int
    target: Float32[np.ndarray, "V 3"]


def _clip_handles(quartic, clip, target, frame, mouth) -> np.ndarray:
    """``CLIP_HANDLES`` farthest points among the mouth vertices the edit moves > 0.5 mm,
    from the one it moves most."""
    neutral = np.asarray(quartic.neutral, np.float32)
    moved = np.linalg.norm(target - clip[frame], axis=1)
    mouth_chin = np.flatnonzero(mouth & (moved > 0.05))
    return mouth_chin[
        farthest_point_vertices(
            neutral[mouth_chin], CLIP_HANDLES, start=int(np.argmax(moved[mouth_chin]))
        )
    ]


def clip_edit_protocol(
    rig: NeuralRig,
    quartic: BlendshapeRig,
    clip_weights: Float[np.ndarray, "F K"],
    options: FitOptions,
) -> tuple[dict, ClipEditRun]:
    """Figure 10: the clip of ``clip_weights`` (F, K) with the jaw opened 0.3 wider at its
    middle frame: handles on the mouth and chin fitted (inside the mouth mask) to that
    frame's target, the edit faded over +-``CLIP_HALF_WINDOW`` frames (``clip_edit``).
    Returns the numbers (the exact zeros outside the window and outside every clamped mask,
    the mouth's error to the target before and after, accelerations in mm/frame^2) and the
    run."""
    clip = evaluate_poses(quartic, clip_weights)
    frame = len(clip) // 2
    mouth = expression_region(quartic, threshold=MOUTH_THRESHOLD_CM)
    wider = clip_weights[frame].copy()
    jaw = list(quartic.names).index("jawOpen")
    wider[jaw] = min(1.0, wider[jaw] + 0.3)
    target = evaluate_poses(quartic, wider[None])[0]
    handles = rig.handles(_clip_handles(quartic, clip, target, frame, mouth))
    solution = pose_a_to_b(
        rig,
        handles,
        clip[frame],
        target,
        CLIP_RADIUS_CM,
        FALLOFF_PER_CM,
        fit=True,
        region=mouth,
        options=options,
    )
    displacements = np.asarray(solution.displacements)
    edited = clip_edit(
        rig, clip, frame, handles, displacements, CLIP_RADIUS_CM, FALLOFF_PER_CM, CLIP_HALF_WINDOW
    )
    lo, hi = edited.window
    outside_window = np.r_[0:lo, hi + 1 : len(clip)]
    mask = np.asarray(
        influence_mask(handles.distance, CLIP_RADIUS_CM, FALLOFF_PER_CM, rig.model.clamp)
    )
    outside_mask = mask.max(axis=1) == 0
    numbers = {
        "outside_window_max_mm": float(
            _error_mm(edited.clip[outside_window], clip[outside_window]).max(initial=0.0)
        ),
        "outside_window_bit_identical": bool(
            np.array_equal(edited.clip[outside_window], clip[outside_window])
        ),
        "outside_mask_max_mm": float(_error_mm(edited.clip, clip)[:, outside_mask].max()),
        "edit_error_mm": float(_error_mm(edited.clip[frame], target)[mouth].mean()),
        "edit_error_before_mm": float(_error_mm(clip[frame], target)[mouth].mean()),
        "max_acceleration_before": max_acceleration(clip) * CM_TO_MM,
        "max_acceleration_after": max_acceleration(edited.clip) * CM_TO_MM,
        "max_acceleration_of_the_edit": max_acceleration(edited.clip - clip) * CM_TO_MM,
        "frame": int(frame),
        "window": [int(lo), int(hi)],
        "handles": CLIP_HANDLES,
        "radius_cm": CLIP_RADIUS_CM,
        "outside_mask_vertices": int(outside_mask.sum()),
    }
    return numbers, ClipEditRun(clip, edited, frame, target)


# --------------------------------------------------------------------------- dialogue


@dataclasses.dataclass(frozen=True)
class DialogueRun:
    """``dialogue_table``'s source and target clips (F, V, 3), the mouth handles, and each
    CANRig output ("direct", "fitted": (F, V, 3)), all in cm."""

    source: Float32[np.ndarray, "F V 3"]
    target: Float32[np.ndarray, "F V 3"]
    handles: Handles
    outputs: dict[str, Float32[np.ndarray, "F V 3"]]


def dialogue_handle_vertices(
    rig: NeuralRig, mouth: Bool[np.ndarray, " V"]
) -> Int[np.ndarray, " H"]:
    """(``DIALOGUE_HANDLES``,) farthest points among the mouth vertices farther than the
    masks' reach from the mouth mask's border (``interior_vertices``), so no handle's mask
    leaves the mouth."""
    reach = float(influence_reach(DIALOGUE_RADIUS_CM, FALLOFF_PER_CM, rig.model.clamp))
    interior = interior_vertices(rig, mouth, reach)
    return interior[farthest_point_vertices(np.asarray(rig.canonical)[interior], DIALOGUE_HANDLES)]


def _gbs_baselines(quartic, source, target, mouth, mouth_index, seed) -> dict:
    """Table 6's global-blendshape rows: the mouth handles moved plus 140 geodesic farthest
    points off the mouth kept still, with the 19-shape basis and with ICT's 53 expressions."""
    neutral = np.asarray(quartic.neutral, np.float32)
    off_mouth = np.flatnonzero(~mouth)
    still = off_mouth[farthest_point_vertices(neutral[off_mouth], 200 - DIALOGUE_HANDLES)]
    index = np.concatenate([mouth_index, still])
    moved = np.arange(len(index)) < DIALOGUE_HANDLES
    training = random_sparse_poses(np.random.default_rng([seed, 2]), 200, quartic.names)
    basis_19, _ = pbs_basis(neutral, evaluate_poses(quartic, training), 19)
    baselines = {}
    for name, basis in (("gbs_19", basis_19), ("gbs_ict_53", np.asarray(quartic.deltas))):
        inverted, edited = global_blendshape_dialogue(basis, neutral, source, target, index, moved)
        inverted, edited = np.asarray(inverted), np.asarray(edited)
        baselines[name] = {
            "rig_inversion_mm": float(_error_mm(inverted, source).mean()),
            "mouth_difference_mm": float(_error_mm(edited, target)[:, mouth].mean()),
            "rest_of_face_change_mm": float(_error_mm(edited, source)[:, ~mouth].mean()),
            "rest_of_face_change_max_mm": float(_error_mm(edited, source)[:, ~mouth].max()),
        }
    return baselines


GBS_PROTOCOL = (
    "GBS (CANRig Table 6): basis offsets fitted by ridge least squares "
    "(1e-3 x the mean diagonal) at 200 handles: the 60 mouth handles (moved to the target "
    "frame) and 140 geodesic farthest points off the mouth mask (kept at the source); "
    "gbs_19: the neutral + 18 farthest-point shapes of 200 random sparse poses (not the "
    "held-out ones); gbs_ict_53: the rig's 53 linear expressions. Means over frames and "
    "vertices (rest of face: mean, and its max beside it); CANRig's inversion and rest of "
    "face are maxima (0.0)"
)


def dialogue_table(
    rig: NeuralRig,
    quartic: BlendshapeRig,
    capture: Float[np.ndarray, "F K"],
    mouth: Bool[np.ndarray, " V"],
    options: FitOptions,
    n_frames: int,
    seed: int,
) -> tuple[dict, DialogueRun]:
    """Dialogue replacement (Figure 12 / Table 6) of ``n_frames`` capture frames from 90
    (source) by those from 135 (target) inside the ``mouth`` mask (V,): CANRig direct and
    fitted at ``DIALOGUE_HANDLES`` mouth handles, and the global-blendshape baselines (GBS)
    with the 19-shape basis and with ICT's 53 expressions, each source frame inverted by a
    fit at 200 handles over the face, then refitted with the mouth handles at the target.
    Returns the numbers (mm) and the run."""
    s0, t0 = DIALOGUE_SOURCE_FRAME, DIALOGUE_TARGET_FRAME
    source = evaluate_poses(quartic, capture[s0 : s0 + n_frames])
    target = evaluate_poses(quartic, capture[t0 : t0 + n_frames])
    mouth_index = dialogue_handle_vertices(rig, mouth)
    handles = rig.handles(mouth_index)
    dialogue, outputs = {}, {}
    for kind in ("direct", "fitted"):
        out = dialogue_replacement(
            rig,
            source,
            target,
            handles,
            DIALOGUE_RADIUS_CM,
            FALLOFF_PER_CM,
            fit=kind == "fitted",
            region=mouth,
            options=options,
        )
        outputs[kind] = out
        dialogue[kind] = {
            "mouth_difference_mm": float(_error_mm(out, target)[:, mouth].mean()),
            "rest_of_face_change_mm": float(_error_mm(out, source)[:, ~mouth].max()),
        }
    zero = dialogue_replacement(rig, source, source, handles, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM)
    results = {
        "rig_inversion_mm": float(_error_mm(zero, source).max()),
        "mouth_difference_mm": dialogue["direct"]["mouth_difference_mm"],
        "rest_of_face_change_mm": dialogue["direct"]["rest_of_face_change_mm"],
        "fitted": dialogue["fitted"],
        "baselines": _gbs_baselines(quartic, source, target, mouth, mouth_index, seed),
        "baseline_protocol": GBS_PROTOCOL,
        "source_mouth_difference_mm": float(_error_mm(source, target)[:, mouth].mean()),
        "frames": {"source": [s0, s0 - 1 + n_frames], "target": [t0, t0 - 1 + n_frames]},
        "mouth_mask_vertices": int(mouth.sum()),
        "mouth_mask": f"expression_region(threshold={MOUTH_THRESHOLD_CM} cm): vertices some "
        "jaw*/mouth* expression of the ict-quartic rig moves more than that and no eye*/brow* "
        "expression does",
        "handles": DIALOGUE_HANDLES,
        "radius_cm": DIALOGUE_RADIUS_CM,
    }
    return results, DialogueRun(source, target, handles, outputs)


# --------------------------------------------------------------------------- table.md


def _a_to_b_rows(table: Mapping) -> list[str]:
    """Table 4's Markdown rows (handles x radius) for one ``a_to_b_table``."""
    lines = [
        "| handles | " + " | ".join(f"{k} ({v:g} cm)" for k, v in RADII_CM.items()) + " |",
        "|---" * (len(RADII_CM) + 1) + "|",
    ]
    for n, row in table.items():
        cells = [
            f"{c['direct_mm']:.3f} / {c['direct_on_fitted_pairs_mm']:.3f} / "
            f"**{c['fitted_mm']:.3f}** / {c['fitted_p95_mm']:.2f} ({c['pairs_fitted']})"
            for c in row.values()
        ]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _floor_rows(floor: Mapping) -> list[str]:
    lines = [
        "**Floor of any result, random_vertices** (mm; vertices beyond every handle's "
        "reach keep A's position whatever the network or the fit; % of vertices unreached "
        "in brackets)",
        "",
        "| handles | " + " | ".join(f"{k} ({v:g} cm)" for k, v in RADII_CM.items()) + " |",
        "|---" * (len(RADII_CM) + 1) + "|",
    ]
    for n, row in floor.items():
        cells = [f"{c['floor_mm']:.3f} ({c['unreached_percent']:.1f} %)" for c in row.values()]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _model_line(model: Mapping) -> str:
    if "selected" in model:
        chosen = model["selected"]
        return (
            "Rig: `LocalFitRig`, no network (beyond the paper): "
            f"{chosen['patches']} patches, neutral + {chosen['basis'] - 1} basis offsets, "
            f"ridge {chosen['ridge']:g}, selected on pairs of training poses."
        )
    trained_on = (
        "random handle sets and radii (the paper's recipe)"
        if model["p_farthest"] == 0 and model["p_eval_radius"] == 0
        else f"{model['p_farthest']:.0%} evaluation handle sets, {model['p_eval_radius']:.0%} "
        "evaluation radii"
    )
    return f"Model trained on {trained_on}, {model['train_steps']} steps."


def _dialogue_rows(dialogue: Mapping) -> list[tuple[str, str]]:
    return [
        ("dialogue: rig inversion (mm)", f"{dialogue['rig_inversion_mm']:g}"),
        (
            "dialogue: mouth difference, direct / fitted / no edit (mm)",
            " / ".join(
                f"{x:.3f}"
                for x in (
                    dialogue["mouth_difference_mm"],
                    dialogue["fitted"]["mouth_difference_mm"],
                    dialogue["source_mouth_difference_mm"],
                )
            ),
        ),
        (
            "dialogue: rest of face change, direct / fitted (mm)",
            f"{dialogue['rest_of_face_change_mm']:g} / "
            f"{dialogue['fitted']['rest_of_face_change_mm']:g}",
        ),
    ]


def _quantity_rows(results: Mapping) -> list[str]:
    """The table of layers, clip edit, dialogue (when run) and timing."""
    layers, clip, timing = results["layers"], results["clip_edit"], results["timing"]
    rows = [
        (
            "layers 20/4cm, 75/2cm, 200/1cm, direct (mm)",
            " / ".join(f"{x:.3f}" for x in layers["direct_mm"]),
        ),
        ("layers, fitted (mm)", " / ".join(f"{x:.3f}" for x in layers["fitted_mm"])),
        ("fitted layers non-increasing on every pair", layers["fitted_non_increasing_every_pair"]),
        (
            "clip edit: outside window max (mm); bit-identical",
            f"{clip['outside_window_max_mm']:g}; {clip['outside_window_bit_identical']}",
        ),
        ("clip edit: outside every clamped mask max (mm)", f"{clip['outside_mask_max_mm']:g}"),
        (
            "clip edit: mouth error to the target at the frame, before -> after (mm)",
            f"{clip['edit_error_before_mm']:.3f} -> {clip['edit_error_mm']:.3f}",
        ),
        (
            "clip: max acceleration before / after / of the edit alone (mm/frame^2)",
            " / ".join(
                f"{clip[k]:.3f}"
                for k in ("max_acceleration_before", "max_acceleration_after")
                + ("max_acceleration_of_the_edit",)
            ),
        ),
        *(_dialogue_rows(results["dialogue"]) if "dialogue" in results else []),
        ("fitted A to B, 200 handles, 2 cm (ms, one call)", f"{timing['fit_ms_200_handles']:.0f}"),
        (
            "direct A to B, 200 handles, 2 cm (ms, one call)",
            f"{timing['direct_ms_200_handles']:.1f}",
        ),
    ]
    if "dialogue_ms_per_frame" in timing:
        rows.append(
            (
                "dialogue replacement, batched over the clip (ms per frame)",
                f"{timing['dialogue_ms_per_frame']:.1f}",
            )
        )
    return ["| quantity | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows]


def _table6_rows(results: Mapping) -> list[str]:
    """Table 6 (the dialogue against its GBS baselines), when the dialogue has them."""
    dialogue = results.get("dialogue", {})
    baselines = dialogue.get("baselines")
    if not baselines:
        return []
    rig_name = "LocalFitRig" if "selected" in results["protocol"]["model"] else "CANRig"
    lines = [
        "",
        "Dialogue replacement as Table 6 (mm; CANRig's inversion and rest of face are "
        "maxima, the baselines' means with the max in brackets)",
        "",
        "| method | rig inversion | mouth difference | rest of face change |",
        "|---|---|---|---|",
    ]
    for kind, numbers in (("direct", dialogue), ("fitted", dialogue["fitted"])):
        lines.append(
            f"| {rig_name}, {kind} | {dialogue['rig_inversion_mm']:g} | "
            f"{numbers['mouth_difference_mm']:.3f} | {numbers['rest_of_face_change_mm']:g} |"
        )
    for name, b in baselines.items():
        lines.append(
            f"| {name} | {b['rig_inversion_mm']:.3f} | {b['mouth_difference_mm']:.3f} | "
            f"{b['rest_of_face_change_mm']:.3f} ({b['rest_of_face_change_max_mm']:.2f}) |"
        )
    return lines


def workflows_markdown(results: Mapping) -> str:
    """table.md of a workflows results.json: Table 4 per placement protocol (with its floor
    when computed), layers, clip edit, dialogue (when run), timing and Table 6."""
    protocol = results["protocol"]
    lines = [
        f"Pose A to pose B (Table 4 protocol): {protocol['pairs']} random pairs of "
        f"held-out ict-quartic poses (fitted on the first {protocol['fitted_pairs']}), "
        f"mean per-vertex error to B over the 9,409 face vertices (mm), falloff 3/cm. "
        + _model_line(protocol["model"]),
        "",
    ]
    for name, table in results["a_to_b"].items():
        lines += [
            f"**{name}**: direct (all pairs) / direct on the fitted pairs / **fitted** / "
            "fitted p95 (mm); fitted pairs per cell in brackets",
            "",
            *_a_to_b_rows(table),
        ]
    floor = results.get("a_to_b_floor", {}).get("random_vertices")
    if floor:
        lines += _floor_rows(floor)
    lines += _quantity_rows(results) + _table6_rows(results)
    return "\n".join(lines) + "\n"


__all__ = [
    "CLIP_HALF_WINDOW",
    "CLIP_HANDLES",
    "CLIP_RADIUS_CM",
    "DIALOGUE_HANDLES",
    "DIALOGUE_RADIUS_CM",
    "DIALOGUE_SOURCE_FRAME",
    "DIALOGUE_TARGET_FRAME",
    "DISTANCE_LIMIT_CM",
    "FALLOFF_PER_CM",
    "GBS_PROTOCOL",
    "HANDLE_COUNTS",
    "LAYER_SCHEDULE",
    "LOCAL_FIT_DESCRIPTION",
    "LOCAL_FIT_GRID",
    "MOUTH_THRESHOLD_CM",
    "ClipEditRun",
    "DialogueRun",
    "WorkflowData",
    "a_to_b_cell",
    "a_to_b_table",
    "clip_edit_protocol",
    "dialogue_handle_vertices",
    "dialogue_table",
    "layers_protocol",
    "local_fit_from_selection",
    "local_fit_training_shapes",
    "network_rig",
    "random_pairs",
    "results_of_the_same_pairs",
    "select_local_fit",
    "table4_protocol",
    "unreached_floor",
    "workflow_data",
    "workflows_markdown",
]
