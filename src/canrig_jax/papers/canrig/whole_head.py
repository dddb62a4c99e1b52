"""Evaluation protocols of patch blendshapes (PBS) on the whole ICT head: the head, its patch
layout, basis, training and held-out shapes and the masks' graph (``whole_head``); how well
PBS represents held-out shapes; Table 5 (global blendshapes, the local fit alone, the trained
networks) broken down by region with each region's reach from the handles; Table 6
(dialogue replacement on the whole head) with the floor no CANRig-PBS result can beat, and
its variant over the number of mouth handles.

The experiment scripts (``experiments/canrig_pbs.py``, ``canrig_pbs_train.py``,
``canrig_pbs_table6_sweep.py``) call these; the tests call them here. Shapes and distances in
cm, errors in mm.
"""

import argparse
import dataclasses
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Float32, Int

from ..._checkpoint import parameter_count
from ..._cli import add_dataclass_options, from_args
from ..._metrics import CM_TO_MM
from ...autorig._data import head_rig
from ...canrig._layout import influence_reach
from ...canrig._masks import CLAMP, influence_mask
from ...canrig._workflows import expression_region
from ...data import ICTFaceModel, load_ict, load_livelinkface
from ...mesh import attached_edge_graph, bridged_edge_graph, edge_graph, farthest_point_vertices
from ...pbs._basis import (
    PatchLayout,
    fit_pbs,
    global_blendshape_dialogue,
    global_blendshape_fit,
    local_pbs_fit,
    patch_layout,
    pbs_basis,
    pbs_shape,
)
from ...pbs._model import PBS_VARIANTS, AbstractCANRigPBS, ShapeTransformer
from ...pbs._train import (
    PBSTrainingSet,
    build_pbs_training_set,
    load_pbs_model,
    pbs_reconstruct,
    seed_distances,
)
from ...rig import BlendshapeRig, evaluate_batch, ict_quartic_rig, random_sparse_poses
from ._pbs_checks import check_pbs_training_matches, reach_floor
from ._splits import held_out_poses, split_capture

SKIN = ("Face", "Head and Neck")
"""The ICT parts Table 5's handles (and the training handles) are drawn from."""
MOUTH_INTERIOR = ("Mouth socket", "Gums and tongue", "Teeth")
REGIONS = {
    "face": ("Face",),
    "mouth_interior": MOUTH_INTERIOR,
    "eye_parts": (
        "Eye socket left",
        "Eye socket right",
        "Lacrimal fluid left",
        "Lacrimal fluid right",
        "Eye blend left",
        "Eye blend right",
        "Eye occlusion left",
        "Eye occlusion right",
        "Eyelashes left",
        "Eyelashes right",
    ),
    "head_and_neck": ("Head and Neck",),
}
"""Table 5 broken down by where the error is (ICT part names)."""
GRAPHS = ("bridged", "mesh", "attached")
HANDLE_REGIONS = ("skin", "moving")
MODELS_DIR = "models"
"""Trained models live in ``OUT/models/NAME[TAG]/checkpoint.eqx`` (with their train.json)."""
TABLE5_MODELS = ("per_patch", "shape_transformer")
LOCAL_FIT_RIDGE = 1e-2
"""``local_pbs_fit``'s ridge for Table 5's no-network row (CANRigPBS's initial one)."""
FIGURE8_TAG = "_fig8"
"""Figure 8's runs: 1,000 steps of the same 2,000-step schedule, in ``NAME + FIGURE8_TAG``."""
FIGURE8_MODELS = tuple(PBS_VARIANTS)
"""Figure 8's rows: the CANRig-PBS variants (``pbs.PBS_MODELS`` without the Shape
Transformer)."""
EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM = 4.0, 1.0
"""Table 5's masks (CANRig-PBS)."""
POOL_SIZE = 4096
"""Candidate handle vertices for training."""
DIALOGUE_HANDLES, DIALOGUE_RADIUS_CM, DIALOGUE_FALLOFF = 60, 1.5, 3.0
"""Table 6's mouth handles and their masks (cm, per cm)."""
DIALOGUE_REACH_CM = float(influence_reach(DIALOGUE_RADIUS_CM, DIALOGUE_FALLOFF, CLAMP))
"""Beyond this distance from a mouth handle its clamped mask is exactly 0."""
MOUTH_THRESHOLD_CM = 0.3
"""The mouth mask's threshold (as the workflows experiment's)."""
DIALOGUE_SOURCE_FRAME, DIALOGUE_TARGET_FRAME = 90, 135


# --------------------------------------------------------------------------- the whole head


@dataclasses.dataclass(frozen=True)
class WholeHeadOptions:
    """What defines the whole-head setup: the patch layout (``patches``, ``rings``), the
    basis size, the random training poses beside the capture's first half, Table 5's handle
    count, where handles are drawn (``handles_on``: the skin or every moving part) and the
    masks' geodesics (``graph``; ``attach`` / ``attach_onto``: the ICT parts of the
    ``"attached"`` graph)."""

    patches: int = 457
    basis: int = 19
    rings: int = 3
    handles: int = 265
    n_random: int = 400
    graph: str = "bridged"
    attach: tuple[str, ...] = MOUTH_INTERIOR
    attach_onto: tuple[str, ...] = ("Face",)
    handles_on: str = "skin"

    def __post_init__(self):
        if self.graph not in GRAPHS:
            raise ValueError(f"graph: expected one of {GRAPHS}, got {self.graph!r}")
        if self.handles_on not in HANDLE_REGIONS:
            raise ValueError(
                f"handles_on: expected one of {HANDLE_REGIONS}, got {self.handles_on!r}"
            )
        for name in ("patches", "basis", "rings", "handles", "n_random"):
            if getattr(self, name) < (0 if name in ("rings", "n_random") else 1):
                raise ValueError(f"{name}: expected a positive count, got {getattr(self, name)}")

    def quick(self) -> "WholeHeadOptions":
        """``--quick``: 60 patches, 60 random training poses."""
        return dataclasses.replace(self, patches=60, n_random=60)


_OPTION_HELP = {
    "graph": "geodesics of the masks: 'bridged' (mesh.bridged_edge_graph: teeth, gums, "
    "eyelashes and the other floating parts reach the skin handles), 'mesh' (edges "
    "only: those parts are out of every handle's reach) or 'attached' (a variant: bridged, "
    "and the --attach parts one-way exits onto the nearest vertex of the --attach-onto "
    "parts, mesh.attached_edge_graph)",
    "attach": "--graph attached: the ICT parts measured from the --attach-onto parts",
    "attach_onto": "--graph attached: the ICT parts the --attach parts exit onto "
    "(nearest vertex, 3D)",
    "handles_on": "where training handles are drawn and Table 5's handles placed: the skin "
    "(Face, Head and Neck; the protocol) or every part that moves (a variant: handles may sit "
    "on the teeth, gums, eyelashes)",
}


def add_whole_head_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add every field of ``WholeHeadOptions`` to ``parser`` as ``--field-name``, and
    ``--quick``. Read them back with ``whole_head_options_from_args``."""
    add_dataclass_options(
        parser,
        WholeHeadOptions,
        choices={"graph": GRAPHS, "handles_on": HANDLE_REGIONS},
        help=_OPTION_HELP,
    )
    parser.add_argument("--quick", action="store_true", help="60 patches, 60 training poses")
    return parser


def whole_head_options_from_args(args: argparse.Namespace) -> WholeHeadOptions:
    """The ``WholeHeadOptions`` of a namespace parsed by ``add_whole_head_options``'s parser
    (``--quick``: ``WholeHeadOptions.quick``)."""
    options = from_args(WholeHeadOptions, args)
    return options.quick() if getattr(args, "quick", False) else options


@dataclasses.dataclass(frozen=True)
class WholeHead:
    """The whole ICT head (N vertices) set up for PBS: the ICT model and its whole-head rig,
    the neutral (N, 3), faces, the vertices some expression moves (``active``, (N,)) and
    their parts' names, the patch layout (P patches) and the seconds it took, the capture on
    the rig's channels (F, K) and its training half, the training and held-out poses and
    shapes ((T, N, 3), cm), the PBS basis (B, N, 3) and the training shapes it was picked
    from, the skin (N,), where handles are drawn (N,) and the masks' edge graph."""

    options: WholeHeadOptions
    model: ICTFaceModel
    rig: BlendshapeRig
    neutral: Float32[np.ndarray, "N 3"]
    faces: Int[np.ndarray, "F 3"]
    active: Bool[np.ndarray, " N"]
    parts: list[str]
    layout: PatchLayout
    layout_seconds: float
    capture: Float32[np.ndarray, "C K"]
    capture_train: Float32[np.ndarray, "C_train K"]
    train: Float32[np.ndarray, "T K"]
    test: Float32[np.ndarray, "S K"]
    train_shapes: Float32[np.ndarray, "T N 3"]
    test_shapes: Float32[np.ndarray, "S N 3"]
    basis: Float32[np.ndarray, "Bm1 N 3"]
    picked: Int[np.ndarray, " Bm1"]
    skin: Bool[np.ndarray, " N"]
    handle_region: Bool[np.ndarray, " N"]
    graph: sp.csr_matrix


def mask_graph(options: WholeHeadOptions, model: ICTFaceModel) -> sp.csr_matrix:
    """The masks' edge graph (``options.graph``) of the ICT head."""
    neutral, faces = np.asarray(model.neutral, np.float32), np.asarray(model.faces)
    if options.graph == "mesh":
        return edge_graph(neutral, faces)
    graph = bridged_edge_graph(neutral, faces)
    if options.graph == "attached":
        graph = attached_edge_graph(
            graph,
            neutral,
            model.part_mask(options.attach, "--attach"),
            model.part_mask(options.attach_onto, "--attach-onto"),
        )
    return graph


def whole_head(
    options: WholeHeadOptions,
    data_dir: str | Path | None = None,
    progress: Callable[[str], object] = print,
) -> WholeHead:
    """The whole ICT head of ``options``: the linear ICT rig on all vertices plus the
    ict-quartic correctives on the face part; training poses: the capture's first half and
    ``n_random`` random sparse poses (seed 0), held out: its second half and 100 random
    sparse poses of another seed (``held_out_poses``); the basis is picked from the training
    shapes (``pbs_basis``)."""
    model = load_ict(data_dir, parts=None)
    face_rig, _ = ict_quartic_rig(data_dir, progress=False)
    rig = head_rig(face_rig, model)
    neutral = np.asarray(model.neutral, np.float32)
    faces = np.asarray(model.faces)
    active = np.linalg.norm(model.deltas, axis=-1).max(axis=0) > 0  # not the eyeballs
    parts = [
        name
        for name, (a, b) in zip(model.part_names, model.part_vertex_range, strict=True)
        if active[a:b].any()
    ]
    start = time.perf_counter()
    layout = patch_layout(neutral, faces, options.patches, rings=options.rings, active=active)
    layout_s = time.perf_counter() - start
    progress(f"layout: {options.patches} patches over {active.sum()} vertices in {layout_s:.1f} s")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(data_dir).weights_for(rig.names, missing="zero")
    capture_train, capture_test = split_capture(capture)
    rng = np.random.default_rng(0)
    train = np.concatenate(
        [capture_train, random_sparse_poses(rng, options.n_random, rig.names, n_active=(4, 10))]
    ).astype(np.float32)
    test = held_out_poses(capture_test, rig.names)
    train_shapes = np.asarray(evaluate_batch(rig, train, chunk=32), np.float32)
    test_shapes = np.asarray(evaluate_batch(rig, test, chunk=32), np.float32)
    basis, picked = pbs_basis(neutral, train_shapes, options.basis)
    skin = model.part_mask(SKIN)
    return WholeHead(
        options=options,
        model=model,
        rig=rig,
        neutral=neutral,
        faces=faces,
        active=active,
        parts=parts,
        layout=layout,
        layout_seconds=layout_s,
        capture=capture,
        capture_train=capture_train,
        train=train,
        test=test,
        train_shapes=train_shapes,
        test_shapes=test_shapes,
        basis=basis,
        picked=picked,
        skin=skin,
        handle_region=skin if options.handles_on == "skin" else active,
        graph=mask_graph(options, model),
    )


def pbs_training_set(head: WholeHead) -> tuple[PBSTrainingSet, Float[np.ndarray, "P N"]]:
    """The training set of the head (``build_pbs_training_set``: up to ``POOL_SIZE`` random
    candidate handles in the handle region, seed [0, 3]) and the (P, N) seed distances along
    the masks' graph (cm)."""
    region = head.handle_region
    pool = np.random.default_rng([0, 3]).choice(
        np.flatnonzero(region), min(POOL_SIZE, int(region.sum())), replace=False
    )
    distances = seed_distances(head.layout, head.graph)
    data = build_pbs_training_set(
        head.neutral, head.train_shapes, head.layout, head.basis, distances, pool
    )
    return data, distances


def check_model_matches(options: WholeHeadOptions, folder: str | Path) -> None:
    """Refuse to resume or evaluate the model in ``folder`` if it was trained with other
    ``handles_on`` / ``graph`` options (``check_pbs_training_matches``)."""
    check_pbs_training_matches(
        folder,
        handles_on=options.handles_on,
        graph=options.graph,
        attach=options.attach,
        attach_onto=options.attach_onto,
    )


# --------------------------------------------------------------------------- Table 5


def pbs_representation(
    head: WholeHead,
) -> tuple[dict, Float[np.ndarray, "S N"], Float[np.ndarray, "S P B"]]:
    """How well PBS represents the held-out shapes (per-patch least squares, ``fit_pbs``):
    the summary (the layout's patch sizes, mean / p95 / face / max error in mm), the (T, N)
    per-vertex errors (mm) and the fitted weights (T, P, B - 1)."""
    layout, neutral, basis, model = head.layout, head.neutral, head.basis, head.model
    sizes = np.array([len(v) for v in layout.patch_vertices()])
    fitted = fit_pbs(layout, neutral, basis, head.test_shapes)
    represented = np.asarray(pbs_shape(layout, neutral, basis, fitted))
    error = np.linalg.norm(represented - head.test_shapes, axis=-1) * CM_TO_MM
    face = slice(*model.part_vertex_range[0])
    options = head.options
    return (
        {
            "patches": options.patches,
            "basis": options.basis,
            "rings": options.rings,
            "parts": head.parts,
            "active_vertices": int(head.active.sum()),
            "patch_size": {
                "min": int(sizes.min()),
                "median": float(np.median(sizes)),
                "max": int(sizes.max()),
            },
            "max_patches_per_vertex": int(layout.vertex_patches.shape[1]),
            "basis_training_index": head.picked.tolist(),
            "fit_mean_mm": float(error.mean()),
            "fit_p95_mm": float(np.percentile(error, 95)),
            "fit_face_mean_mm": float(error[:, face].mean()),
            "fit_max_mm": float(error.max()),
            "layout_seconds": head.layout_seconds,
        },
        error,
        np.asarray(fitted),
    )


def table5_handles(head: WholeHead) -> Int[np.ndarray, " H"]:
    """Table 5's ``options.handles`` handles: geodesic farthest points over the handle
    region along its own edges (the skin: Face, Head and Neck; ``handles_on="moving"``:
    every part that moves)."""
    region = head.handle_region
    region_index = np.flatnonzero(region)
    local = np.full(len(head.neutral), -1)
    local[region_index] = np.arange(len(region_index))
    region_faces = local[head.faces[region[head.faces].all(axis=1)]]
    graph = edge_graph(head.neutral[region_index], region_faces)
    return region_index[
        farthest_point_vertices(head.neutral[region_index], head.options.handles, graph=graph)
    ]


def region_errors(model: ICTFaceModel, error_mm: Float[np.ndarray, "T N"]) -> dict:
    """Per region of ``REGIONS``: the mean per-vertex error (mm) over its vertices, its share
    of the whole-head mean (its error summed over its vertices / all vertices; the shares of
    disjoint regions covering every moving vertex sum to the mean) and its vertex count."""
    n = error_mm.shape[1]
    out = {}
    for region, parts in REGIONS.items():
        index = np.flatnonzero(model.part_mask(parts))
        part = error_mm[:, index]
        out[region] = {
            "mean_mm": float(part.mean()),
            "share_of_mean_mm": float(part.sum(axis=1).mean() / n),
            "vertices": int(len(index)),
        }
    return out


def _row(model: ICTFaceModel, error_mm: np.ndarray, **extra) -> dict:
    """A Table 5 row: the mean and std over shapes of the per-shape mean error (mm), by
    region."""
    per_shape = error_mm.mean(axis=1)
    return {
        "mean_mm": float(per_shape.mean()),
        "std_mm": float(per_shape.std()),
        **extra,
        "regions": region_errors(model, error_mm),
    }


def table5_baselines(head: WholeHead, handles: Int[np.ndarray, " H"]) -> dict:
    """Table 5's rows without training: global blendshapes fitted at the handles (the PBS
    basis, ICT's 53 expressions; reconstruction relative to the neutral, error over every
    vertex) and no motion (the neutral)."""
    neutral, test_shapes = head.neutral, head.test_shapes
    offsets = test_shapes - neutral
    table5 = {}
    for name, shapes in (("gbs_pbs_basis", head.basis), ("gbs_ict_53", head.model.deltas)):
        shapes = np.asarray(shapes)
        weights = global_blendshape_fit(shapes, handles, offsets[:, handles])
        predicted = neutral + np.einsum("tb,bnk->tnk", np.asarray(weights), shapes)
        error_mm = np.linalg.norm(predicted - test_shapes, axis=-1) * CM_TO_MM
        table5[name] = _row(head.model, error_mm, train_minutes=0.0, basis_size=len(shapes))
    no_motion_mm = np.linalg.norm(offsets, axis=-1) * CM_TO_MM
    table5["no_motion"] = _row(head.model, no_motion_mm, train_minutes=0.0)
    return table5


def handle_reach(head: WholeHead, handle_distance: Float[np.ndarray, "P H"]) -> dict:
    """Per region of ``REGIONS``: how far the patches seeded there lie from Table 5's nearest
    handle along the masks' graph (cm; median, max), and the fraction within the masks'
    radius and within their reach (the distance where the clamped mask becomes exactly 0).
    ``handle_distance``: (P, H) from each patch seed to each handle (cm)."""
    seeds = np.asarray(head.layout.seeds)
    nearest = np.asarray(handle_distance).min(axis=1)  # (P,)
    reach = float(influence_reach(EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP))
    out = {"radius_cm": EVAL_RADIUS_CM, "reach_cm": reach, "regions": {}}
    for region, parts in REGIONS.items():
        inside = head.model.part_mask(parts)[seeds]
        d = nearest[inside]
        if not len(d):  # no patch seeded there (--quick's 60 patches)
            out["regions"][region] = {"patches": 0}
            continue
        out["regions"][region] = {
            "patches": int(inside.sum()),
            "nearest_handle_median_cm": float(np.median(d)),
            "nearest_handle_max_cm": float(d.max()),
            "within_radius": float(np.mean(d < EVAL_RADIUS_CM)),
            "within_reach": float(np.mean(d < reach)),
        }
    return out


def table5_reconstruct(
    net: AbstractCANRigPBS | ShapeTransformer,
    data: PBSTrainingSet,
    handles: Int[ArrayLike, " H"],
    handle_distance: Float[ArrayLike, "P H"],
    targets: Float[ArrayLike, "F N 3"],
    queries: Float[Array, "..."] | None = None,
) -> Float[Array, "F N 3"]:
    """Table 5's reconstruction: base the neutral, the handles moved to each target, masks of
    radius ``EVAL_RADIUS_CM`` and falloff ``EVAL_FALLOFF_PER_CM`` (``pbs_reconstruct``)."""
    return pbs_reconstruct(
        net,
        data,
        jnp.asarray(handles),
        jnp.asarray(handle_distance),
        data.neutral,
        jnp.asarray(targets),
        EVAL_RADIUS_CM,
        EVAL_FALLOFF_PER_CM,
        queries,
    )


def table5_trained_row(
    head: WholeHead,
    data: PBSTrainingSet,
    checkpoint: str | Path,
    handles: Int[np.ndarray, " H"],
    handle_distance: Float[np.ndarray, "P H"],
) -> tuple[AbstractCANRigPBS | ShapeTransformer, dict]:
    """The trained model of ``checkpoint`` (checked to match the head's options) and its
    Table 5 row on the held-out shapes: errors by region, training minutes and steps,
    parameters (and its trained ridge when it has the local prior)."""
    check_model_matches(head.options, Path(checkpoint).parent)
    net, state = load_pbs_model(checkpoint, head.neutral, head.layout.n_patches, len(head.basis))
    shapes = np.asarray(table5_reconstruct(net, data, handles, handle_distance, head.test_shapes))
    error_mm = np.linalg.norm(shapes - head.test_shapes, axis=-1) * CM_TO_MM
    row = _row(
        head.model,
        error_mm,
        train_minutes=float(state["seconds"] / 60),
        steps=int(state["step"]),
        parameters=parameter_count(net),
    )
    log_ridge = net.log_ridge if isinstance(net, AbstractCANRigPBS) else None
    if log_ridge is not None:  # a local_prior model
        row["local_prior_ridge"] = float(jnp.exp(log_ridge))
    return net, row


def table5_local_fit(
    head: WholeHead,
    handles: Int[np.ndarray, " H"],
    handle_distance: Float[np.ndarray, "P H"],
    ridge: float,
) -> dict:
    """Table 5's no-network row: ``local_pbs_fit`` (each patch a ridge fit of the basis to
    the handle offsets its masks see) at ``ridge``."""
    neutral, basis, layout = head.neutral, head.basis, head.layout
    offsets = head.test_shapes - neutral
    mask = influence_mask(jnp.asarray(handle_distance), EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP)
    weights = local_pbs_fit(basis[:, handles], offsets[:, handles], mask, ridge)
    error_mm = (
        np.stack(
            [
                np.linalg.norm(np.asarray(pbs_shape(layout, neutral, basis, w)) - shape, axis=-1)
                for w, shape in zip(np.asarray(weights), head.test_shapes, strict=True)
            ]
        )
        * CM_TO_MM
    )
    return _row(head.model, error_mm, train_minutes=0.0, ridge=ridge)


# --------------------------------------------------------------------------- Table 6


@dataclasses.dataclass(frozen=True)
class DialogueClips:
    """Table 6's source and target clips (F, N, 3) on the whole head (cm), the mouth mask
    (N,), the mouth patches (P,: seeded in the mask) and the evaluated mouth region (N,:
    every vertex a mouth patch covers)."""

    source: Float32[np.ndarray, "F N 3"]
    target: Float32[np.ndarray, "F N 3"]
    mouth: Bool[np.ndarray, " N"]
    mouth_patch: Bool[np.ndarray, " P"]
    region: Bool[np.ndarray, " N"]


def dialogue_clips(head: WholeHead, n_frames: int) -> DialogueClips:
    """``DialogueClips`` of ``n_frames`` capture frames from 90 (source) and 135 (target);
    the mouth mask is ``expression_region`` of the whole-head rig (threshold 3 mm)."""
    layout, rig, capture = head.layout, head.rig, head.capture
    s0, t0 = DIALOGUE_SOURCE_FRAME, DIALOGUE_TARGET_FRAME
    source = np.asarray(evaluate_batch(rig, capture[s0 : s0 + n_frames], chunk=16), np.float32)
    target = np.asarray(evaluate_batch(rig, capture[t0 : t0 + n_frames], chunk=16), np.float32)
    mouth = expression_region(rig, threshold=MOUTH_THRESHOLD_CM)
    mouth_patch = mouth[np.asarray(layout.seeds)]
    return DialogueClips(source, target, mouth, mouth_patch, layout.covered_by(mouth_patch))


def mouth_handles(
    neutral: Float[np.ndarray, "N 3"],
    distances: Float[np.ndarray, "P N"],
    mouth: Bool[np.ndarray, " N"],
    mouth_patch: Bool[np.ndarray, " P"],
    count: int,
) -> Int[np.ndarray, " H"]:
    """``count`` mouth handles: farthest points (3D) among the mouth vertices from which no
    patch seeded outside the mouth is within the clamped mask's reach
    (``DIALOGUE_REACH_CM``), so moving them moves no patch outside the mouth."""
    outside_seed_distance = distances[~mouth_patch].min(axis=0)  # (N,) to the nearest
    candidates = np.flatnonzero(mouth & (outside_seed_distance > DIALOGUE_REACH_CM))
    if len(candidates) < count:
        raise ValueError(f"count: {count} mouth handles, only {len(candidates)} candidates")
    return candidates[farthest_point_vertices(neutral[candidates], count)]


def _mean_mm(a, b, where) -> float:
    return float((np.linalg.norm(a - b, axis=-1) * CM_TO_MM)[:, where].mean())


def _table6_network(net, name, data, distances, clips, neutral, mouth_index, all_handles):
    """Table 6's row and edited clip of one trained network: CANRig-PBS moves the mouth
    handles from each source frame (its inversion and rest of face are maxima); the Shape
    Transformer (no base) starts from the neutral with every handle at the frame, the mouth's
    edited (means)."""
    source, target, region = clips.source, clips.target, clips.region
    if name == "per_patch":  # base = each source frame, the mouth handles move
        index, bases = mouth_index, source
        inverted_targets, edited_targets = source, target
    else:  # no base: from the neutral, every handle at the frame (the mouth's edited)
        index, bases = all_handles, neutral
        inverted_targets, edited_targets = source, source.copy()
        edited_targets[:, mouth_index] = target[:, mouth_index]
    inverted, edited = (
        np.asarray(
            pbs_reconstruct(
                net,
                data,
                jnp.asarray(index),
                jnp.asarray(distances[:, index]),
                jnp.asarray(bases),
                jnp.asarray(goal),
                DIALOGUE_RADIUS_CM,
                DIALOGUE_FALLOFF,
            )
        )
        for goal in (inverted_targets, edited_targets)
    )
    inversion = np.linalg.norm(inverted - source, axis=-1) * CM_TO_MM
    change = np.linalg.norm(edited - source, axis=-1) * CM_TO_MM
    row = {
        "rig_inversion_mm": float(inversion.max() if name == "per_patch" else inversion.mean()),
        "mouth_difference_mm": _mean_mm(edited, target, region),
        "rest_of_face_change_mm": float(
            change[:, ~region].max() if name == "per_patch" else change[:, ~region].mean()
        ),
    }
    return row, edited


def table6(
    head: WholeHead,
    data: PBSTrainingSet,
    distances: Float[np.ndarray, "P N"],
    models_dir: str | Path,
    clips: DialogueClips,
    n_mouth: int = DIALOGUE_HANDLES,
    progress: Callable[[str], object] = print,
) -> tuple[dict, dict]:
    """Dialogue replacement (Table 6) on the whole head for the trained models in
    ``models_dir`` (``per_patch``, ``shape_transformer``; a missing one is skipped) and GBS.

    PBS moves whole patches, so the evaluated mouth region is every vertex a patch seeded in
    the mouth mask covers, the rest of the face its complement. CANRig-PBS: ``n_mouth``
    ``mouth_handles`` moved to the target frame, base = the source frame. Shape Transformer
    and GBS (no base shape): the source frame is first inverted from 200 handles (those +
    140 geodesic farthest points on the skin off the mouth region), then the mouth ones
    move. Returns the table (methods, reach floor, frames, protocol) and each method's
    edited clip (F, N, 3) with the clips."""
    neutral, source, target, region = head.neutral, clips.source, clips.target, clips.region
    mouth_index = mouth_handles(neutral, distances, clips.mouth, clips.mouth_patch, n_mouth)
    off = np.flatnonzero(~region & head.skin)
    still = off[farthest_point_vertices(neutral[off], 200 - DIALOGUE_HANDLES)]
    all_handles = np.concatenate([mouth_index, still])
    moved = np.arange(len(all_handles)) < n_mouth
    methods, outputs = {}, {}
    for name in TABLE5_MODELS:
        checkpoint = Path(models_dir) / name / "checkpoint.eqx"
        if not checkpoint.exists():
            continue
        net, _ = load_pbs_model(checkpoint, neutral, head.layout.n_patches, len(head.basis))
        methods[name], outputs[name] = _table6_network(
            net, name, data, distances, clips, neutral, mouth_index, all_handles
        )
    for name, basis in (("gbs_19", head.basis), ("gbs_ict_53", np.asarray(head.rig.deltas))):
        inverted, edited = global_blendshape_dialogue(
            basis, neutral, source, target, all_handles, moved
        )
        inverted, edited = np.asarray(inverted), np.asarray(edited)
        outputs[name] = edited
        methods[name] = {
            "rig_inversion_mm": _mean_mm(inverted, source, slice(None)),
            "mouth_difference_mm": _mean_mm(edited, target, region),
            "rest_of_face_change_mm": _mean_mm(edited, source, ~region),
        }
    floor_mm, unreached = reach_floor(
        head.layout, distances, mouth_index, source, target, region, reach_cm=DIALOGUE_REACH_CM
    )
    n = len(source)
    s0, t0 = DIALOGUE_SOURCE_FRAME, DIALOGUE_TARGET_FRAME
    table = {
        "methods": methods,
        "mouth_handles": int(n_mouth),
        "reach_floor_mm": floor_mm,
        "unreached_region_vertices": unreached,
        "no_edit_mouth_difference_mm": _mean_mm(source, target, region),
        "frames": {"source": [s0, s0 - 1 + n], "target": [t0, t0 - 1 + n]},
        "mouth_region_vertices": int(region.sum()),
        "protocol": "source capture frames 90-134, target 135-179; CANRig-PBS inversion and "
        "rest of face are maxima, the others means; mouth region: every vertex covered by "
        f"a patch seeded in expression_region(threshold={MOUTH_THRESHOLD_CM} cm) "
        f"({int(region.sum())} vertices)",
    }
    progress(f"table 6: {methods}")
    return table, {"source": source, "target": target, "outputs": outputs, "region": region}


def table6_sweep(
    head: WholeHead,
    data: PBSTrainingSet,
    distances: Float[np.ndarray, "P N"],
    models_dir: str | Path,
    clips: DialogueClips,
    counts: Sequence[int],
    progress: Callable[[str], object] = print,
) -> dict:
    """Table 6 with each number of mouth handles of ``counts`` (the 140 still ones
    unchanged): per count, the reach floor and unreached region vertices, each method's
    mouth difference (mm) and CANRig-PBS's largest change outside the region (mm)."""
    if not counts or min(counts) < 1:
        raise ValueError(f"counts: expected counts >= 1, got {list(counts)}")
    sweep = {}
    for count in counts:
        table, _ = table6(head, data, distances, models_dir, clips, count, progress)
        sweep[str(count)] = {
            "reach_floor_mm": table["reach_floor_mm"],
            "unreached_region_vertices": table["unreached_region_vertices"],
            **{k: v["mouth_difference_mm"] for k, v in table["methods"].items()},
            "per_patch_rest_of_face_change_max_mm": table["methods"]
            .get("per_patch", {})
            .get("rest_of_face_change_mm"),
        }
    return sweep


SWEEP_HEADER = "Table 6, a variant: the number of mouth handles"
SWEEP_PROTOCOL = (
    "Table 6's protocol with K mouth handles (farthest points among the same "
    "candidates) instead of 60; the baselines get the same K plus the 140 still handles; "
    "reach_floor_mm: the mouth difference of the region's vertices no moved handle's "
    "clamped mask reaches (they keep the source frame in any CANRig-PBS result)"
)


def sweep_markdown(sweep: Mapping, command: str) -> str:
    """The table.md section of ``table6_sweep`` (headed by ``SWEEP_HEADER``)."""
    first = next(iter(sweep.values()))
    methods = [k for k in ("per_patch", "shape_transformer", "gbs_19", "gbs_ict_53") if k in first]
    lines = [
        f"{SWEEP_HEADER} (`{command}`): the mouth difference (mm) with K mouth handles; "
        "reach floor: the part of it no CANRig-PBS network can remove (region vertices beyond "
        "every moved handle's clamped mask keep the source frame).",
        "",
        "| mouth handles | reach floor (unreached vertices) | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ] + [
        f"| {k} | {v['reach_floor_mm']:.3f} ({v['unreached_region_vertices']}) | "
        + " | ".join(f"{v[m]:.3f}" for m in methods)
        + " |"
        for k, v in sweep.items()
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- table.md

_TABLE5_LABELS = {
    "no_motion": "no motion (the neutral)",
    "gbs_pbs_basis": "GBS, the {n_basis} PBS offsets",
    "gbs_ict_53": "GBS, ICT's 53 expressions",
    "shape_transformer": "Shape Transformer (PBS output)",
    "local_fit": "local PBS fit alone (CANRig-PBS's local prior without the network)",
    "per_patch": "CANRig-PBS (per-patch MLPs)",
}


def _table5_lines(table5: Mapping, n_basis: int) -> tuple[list[str], list[str]]:
    """Table 5's rows and its rows by region."""
    labels = {k: v.format(n_basis=n_basis) for k, v in _TABLE5_LABELS.items()}
    if "local_prior_ridge" in table5.get("per_patch", {}):
        labels["per_patch"] += " + local prior"
    rows = [
        "| method | mean (std) mm | training minutes | steps | parameters |",
        "|---|---|---|---|---|",
    ] + [
        f"| {labels[key]} | {table5[key]['mean_mm']:.3f} ({table5[key]['std_mm']:.3f}) | "
        f"{table5[key]['train_minutes']:.1f} | {table5[key].get('steps', '-')} | "
        f"{table5[key].get('parameters', '-')} |"
        for key in labels
        if key in table5
    ]
    by_region = [
        "| method | " + " | ".join(REGIONS) + " |",
        "|---|" + "---|" * len(REGIONS),
    ] + [
        f"| {label} | "
        + " | ".join(
            f"{table5[key]['regions'][r]['mean_mm']:.3f} "
            f"({table5[key]['regions'][r]['share_of_mean_mm']:.3f})"
            for r in REGIONS
        )
        + " |"
        for key, label in labels.items()
        if key in table5 and "regions" in table5[key]
    ]
    return rows, by_region


def _reach_lines(reach: Mapping, graph: str) -> list[str]:
    return [
        f"Handle reach (--graph {graph}): each region's patches, the distance from "
        "the seed to Table 5's nearest handle along the masks' graph, the fraction within "
        f"the radius ({reach['radius_cm']:.1f} cm) and within the clamped mask's reach "
        f"({reach['reach_cm']:.2f} cm; beyond it no handle moves the patch).",
        "",
        "| region | patches | nearest handle median (max) cm | within radius | within reach |",
        "|---|---|---|---|---|",
    ] + [
        f"| {k} | {v['patches']} | {v['nearest_handle_median_cm']:.2f} "
        f"({v['nearest_handle_max_cm']:.2f}) | {v['within_radius']:.2f} | "
        f"{v['within_reach']:.2f} |"
        for k, v in reach["regions"].items()
        if v["patches"]
    ]


def _figure8_lines(figure8: Mapping) -> list[str]:
    if not figure8:
        return [
            "Figure 8: no variant trained in this folder "
            f"(`canrig_pbs_train.py --model NAME --tag {FIGURE8_TAG}`)."
        ]
    return [
        "Figure 8 (each variant 1,000 steps of the same 2,000-step cosine "
        "schedule; Table 5's protocol):",
        "",
        "| Figure 8 variant | held-out mean (std) mm | steps | parameters |",
        "|---|---|---|---|",
    ] + [
        f"| {k} | {v['mean_mm']:.3f} ({v['std_mm']:.3f}) | {v['steps']} | {v['parameters']} |"
        for k, v in figure8.items()
    ]


def _table6_lines(methods: Mapping, setup: Mapping) -> list[str]:
    lines = [
        "Table 6 (dialogue replacement on the whole head; " + setup.get("protocol", "") + "):",
        "",
        "| method | rig inversion mm | mouth difference mm | rest of face change mm |",
        "|---|---|---|---|",
    ] + [
        f"| {k} | {v['rig_inversion_mm']:.3f} | {v['mouth_difference_mm']:.3f} | "
        f"{v['rest_of_face_change_mm']:.3f} |"
        for k, v in methods.items()
    ]
    lines.append("")
    if "reach_floor_mm" in setup:
        lines += [
            f"Reach floor of CANRig-PBS's mouth difference: {setup['reach_floor_mm']:.3f}"
            f" mm ({setup['unreached_region_vertices']} of the region's vertices lie "
            "beyond every moved handle's clamped mask and keep the source frame).",
            "",
        ]
    return lines


def pbs_markdown(
    results: Mapping, options: WholeHeadOptions, command: str, n_basis: int, n_test: int
) -> str:
    """table.md of a whole-head PBS results.json: the PBS fit, Table 5 (by region, with the
    handles' reach), the layout's timing, Figure 8, Table 6 and the forward passes."""
    pbs, table5, timing = results["pbs"], results["table5"], results["timing"]
    rows, by_region = _table5_lines(table5, n_basis)
    forward = ["| forward pass, 200 handles, whole head | ms |", "|---|---|"] + [
        f"| {k} | {v:.1f} |" for k, v in results["forward_ms"].items()
    ]
    lines = [
        "# Patch blendshapes on the whole ICT head",
        "",
        f"Command: `{command}`",
        "",
        f"PBS: {options.patches} patches over {pbs['active_vertices']} vertices "
        f"({', '.join(pbs['parts'])}), {options.rings} rings of overlap, basis = neutral + "
        f"{n_basis} extreme training shapes.",
        "",
        "| PBS fit of held-out shapes | mean mm | p95 mm | face mean mm | max mm |",
        "|---|---|---|---|---|",
        f"| per-patch least squares | {pbs['fit_mean_mm']:.4f} | {pbs['fit_p95_mm']:.4f} | "
        f"{pbs['fit_face_mean_mm']:.4f} | {pbs['fit_max_mm']:.3f} |",
        "",
        f"Table 5 ({options.handles} handles, reconstruction relative to the neutral, "
        f"{n_test} held-out shapes):",
        "",
        *rows,
        "",
        "Table 5 by region: mean error over the region's vertices, in brackets its share "
        "of the whole-head mean (mm; the shares sum to the mean, the eyeballs do not move). "
        "mouth_interior: " + ", ".join(REGIONS["mouth_interior"]) + "; eye_parts: the eye "
        "sockets, lacrimal fluid, eye blend, eye occlusion and eyelashes.",
        "",
        *by_region,
        "",
        *_reach_lines(results["table5_reach"], options.graph),
        "",
        f"W_layout application: gather form {timing['pbs_shape_gather_ms']:.2f} ms, "
        f"scipy.sparse {timing['pbs_shape_scipy_sparse_ms']:.2f} ms (one shape).",
        "",
        *_figure8_lines(results["figure8"]),
        "",
        *_table6_lines(results["table6"], results["table6_setup"]),
        *forward,
        "",
    ]
    return "\n".join(lines)


def pbs_protocol(options: WholeHeadOptions, head: WholeHead) -> dict:
    """results.json's description of the protocol: shapes, training and held-out poses,
    handles, masks and the timed forward pass."""
    n_train, n = len(head.capture_train), len(head.capture)
    masks = {
        "bridged": "bridged: every floating part's vertices step to their nearest "
        "skin-component vertex)",
        "mesh": "mesh edges only: teeth, gums, eyelashes out of reach)",
        "attached": "bridged, and the vertices of "
        + ", ".join(options.attach)
        + " one-way exits onto their nearest vertex of "
        + ", ".join(options.attach_onto)
        + ", straight through the mouth cavity: mesh.attached_edge_graph)",
    }[options.graph]
    on = f"the skin ({', '.join(SKIN)})" if options.handles_on == "skin" else "every moving part"
    return {
        "shapes": "whole ICT head (26,719 vertices): the ict-quartic rig on the face part "
        "plus ICT's expression deltas elsewhere (autorig.head_rig)",
        "train": f"capture frames 0-{n_train - 1} + {options.n_random} random poses",
        "test": f"capture frames {n_train}-{n - 1} + 100 random poses (held_out_poses)",
        "handles": f"{options.handles} geodesic farthest points on {on}"
        f"; training handles drawn from the same region ({options.handles_on})",
        "masks": f"CANRig-PBS: radius {EVAL_RADIUS_CM} cm, falloff {EVAL_FALLOFF_PER_CM}/cm, "
        "evaluated at each patch's seed vertex (geodesic distance on the whole head, " + masks,
        "forward": "one call at 200 handles (ms, median): the whole-head shape from the "
        "handle displacements; dense_per_vertex_reference: an untrained per-vertex "
        "ShapePreservingCANRig with the same encoder on all 26,719 vertices, dense masks",
    }


__all__ = [
    "DIALOGUE_FALLOFF",
    "DIALOGUE_HANDLES",
    "DIALOGUE_RADIUS_CM",
    "DIALOGUE_REACH_CM",
    "DIALOGUE_SOURCE_FRAME",
    "DIALOGUE_TARGET_FRAME",
    "EVAL_FALLOFF_PER_CM",
    "EVAL_RADIUS_CM",
    "FIGURE8_MODELS",
    "FIGURE8_TAG",
    "GRAPHS",
    "HANDLE_REGIONS",
    "LOCAL_FIT_RIDGE",
    "MODELS_DIR",
    "MOUTH_INTERIOR",
    "MOUTH_THRESHOLD_CM",
    "POOL_SIZE",
    "REGIONS",
    "SKIN",
    "SWEEP_HEADER",
    "SWEEP_PROTOCOL",
    "TABLE5_MODELS",
    "DialogueClips",
    "WholeHead",
    "WholeHeadOptions",
    "add_whole_head_options",
    "check_model_matches",
    "dialogue_clips",
    "handle_reach",
    "mask_graph",
    "mouth_handles",
    "pbs_markdown",
    "pbs_protocol",
    "pbs_representation",
    "pbs_training_set",
    "region_errors",
    "sweep_markdown",
    "table5_baselines",
    "table5_handles",
    "table5_local_fit",
    "table5_reconstruct",
    "table5_trained_row",
    "table6",
    "table6_sweep",
    "whole_head",
    "whole_head_options_from_args",
]
