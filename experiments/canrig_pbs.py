"""Patch blendshapes on the whole ICT head (issue 18, the parts that need no training): the
patch layout, the basis, how well PBS represents held-out shapes, and the global-blendshape
(GBS) rows of Table 5.

    python experiments/canrig_pbs.py --out experiments/results/canrig_pbs

Whole-head shapes: the linear ICT rig on all 26,719 vertices (its 53 expressions; the
ict-quartic correctives exist on the face part only) at the Live Link capture's first half and
400 random sparse poses (training: the basis is picked from them), held out: the capture's
second half and 100 random sparse poses of another seed (``canrig.held_out_poses``).
Writes results.json, table.md, patch_layout.png, pbs_error.png.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from canrig_jax._io import save_json, save_text  # noqa: E402
from canrig_jax._metrics import CM_TO_MM  # noqa: E402
from canrig_jax._provenance import experiment_command, provenance, record_command  # noqa: E402
from canrig_jax._timing import median_ms  # noqa: E402
from canrig_jax.autorig import head_rig  # noqa: E402
from canrig_jax.canrig import (  # noqa: E402
    CLAMP,
    PBS_MODELS,
    PBS_VARIANTS,
    PBSTrainOptions,
    ShapePreservingCANRig,
    build_pbs_training_set,
    check_pbs_training_matches,
    expression_region,
    fit_pbs,
    global_blendshape_dialogue,
    global_blendshape_fit,
    held_out_poses,
    influence_mask,
    influence_reach,
    load_pbs_model,
    local_pbs_fit,
    parameter_count,
    patch_layout,
    pbs_basis,
    pbs_reconstruct,
    pbs_shape,
    reach_floor,
    seed_distances,
    split_capture,
    train_pbs,
    weighted_geodesic_distance,
)
from canrig_jax.data import load_ict, load_livelinkface  # noqa: E402
from canrig_jax.mesh import (  # noqa: E402
    attached_edge_graph,
    bridged_edge_graph,
    edge_graph,
    farthest_point_vertices,
)
from canrig_jax.render import plot_vertex_scalar, save_figure  # noqa: E402
from canrig_jax.rig import evaluate_batch, ict_quartic_rig, random_sparse_poses  # noqa: E402
from canrig_jax.watchdog import run_watched

SKIN = ("Face", "Head and Neck")
MOUTH_INTERIOR = ("Mouth socket", "Gums and tongue", "Teeth")
REGIONS = {  # Table 5 broken down by where the error is (ICT part names)
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


MODELS_DIR = "models"
TABLE5_MODELS = ("per_patch", "shape_transformer")
LOCAL_FIT_RIDGE = 1e-2  # local_pbs_fit's ridge for Table 5's no-network row (CANRigPBS's initial)
FIGURE8_TAG = "_fig8"  # Figure 8's runs: 1,000 steps of the same 2,000-step schedule
EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM = 4.0, 1.0  # Table 5's masks (CANRig-PBS)
POOL_SIZE = 4096  # candidate handle vertices on the skin for training


def _parser():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument("--patches", type=int, default=457)
    parser.add_argument("--basis", type=int, default=19)
    parser.add_argument("--rings", type=int, default=3)
    parser.add_argument("--handles", type=int, default=265)
    parser.add_argument("--n-random", type=int, default=400)
    parser.add_argument("--quick", action="store_true", help="60 patches, 60 training poses")
    parser.add_argument(
        "--train",
        choices=PBS_MODELS,
        default=None,
        help="train this model into OUT/models/NAME/checkpoint.eqx (resumable) and stop",
    )
    parser.add_argument("--minutes", type=float, default=15.0, help="training budget")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--learning-rate", type=float, default=PBSTrainOptions.learning_rate)
    parser.add_argument("--decay-start", type=int, default=0)
    parser.add_argument("--decay-steps", type=int, default=4000)
    parser.add_argument(
        "--tag", default="", help="folder suffix: OUT/models/NAME+TAG (e.g. Figure 8's runs)"
    )
    parser.add_argument(
        "--graph",
        choices=("bridged", "mesh", "attached"),
        default="bridged",
        help="geodesics of the masks: 'bridged' (mesh.bridged_edge_graph: teeth, gums, "
        "eyelashes and the other floating parts reach the skin handles), 'mesh' (edges "
        "only: those parts are out of every handle's reach; the runs before 2026-12-02) or "
        "'attached' (a variant: bridged, and the --attach parts one-way exits onto the "
        "nearest vertex of the --attach-onto parts, mesh.attached_edge_graph)",
    )
    parser.add_argument(
        "--attach",
        nargs="+",
        default=list(MOUTH_INTERIOR),
        help="--graph attached: the ICT parts measured from the --attach-onto parts",
    )
    parser.add_argument(
        "--attach-onto",
        nargs="+",
        default=["Face"],
        help="--graph attached: the ICT parts the --attach parts exit onto (nearest vertex, 3D)",
    )
    parser.add_argument(
        "--handles-on",
        choices=("skin", "moving"),
        default="skin",
        help="where training handles are drawn and Table 5's handles placed: the skin (Face, "
        "Head and Neck; the protocol) or every part that moves (a variant: handles may sit on "
        "the teeth, gums, eyelashes)",
    )
    parser.add_argument(
        "--table6-sweep",
        type=int,
        nargs="+",
        default=None,
        metavar="K",
        help="only Table 6 again with K mouth handles for each K (a variant; the protocol has "
        "60): its reach floor and every method's mouth difference, added to OUT's "
        "results.json (table6_handle_sweep) and table.md; needs OUT's trained checkpoints",
    )
    parser.add_argument(
        "--local-prior",
        action="store_true",
        help="--train a CANRig-PBS variant: the network corrects a per-patch masked ridge fit "
        "of the basis to the handles it sees (CANRigPBS local_prior; beyond the paper)",
    )
    parser.add_argument("--no-progress", action="store_true")
    return parser


def _whole_head(args):
    """The whole ICT head, its patch layout, training and held-out shapes, PBS basis."""
    model = load_ict(args.data_dir, parts=None)
    face_rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    rig = head_rig(face_rig, model)
    neutral = np.asarray(model.neutral, np.float32)
    faces = np.asarray(model.faces)
    motion = np.linalg.norm(model.deltas, axis=-1).max(axis=0)
    active = motion > 0  # every vertex some expression moves (not the eyeballs)
    parts = [
        name
        for name, (a, b) in zip(model.part_names, model.part_vertex_range, strict=True)
        if active[a:b].any()
    ]
    start = time.perf_counter()
    layout = patch_layout(neutral, faces, args.patches, rings=args.rings, active=active)
    layout_s = time.perf_counter() - start
    print(f"layout: {args.patches} patches over {active.sum()} vertices in {layout_s:.1f} s")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    capture_train, capture_test = split_capture(capture)
    rng = np.random.default_rng(0)
    train = np.concatenate(
        [capture_train, random_sparse_poses(rng, args.n_random, rig.names, n_active=(4, 10))]
    ).astype(np.float32)
    test = held_out_poses(capture_test, rig.names)
    train_shapes = np.asarray(evaluate_batch(rig, train, chunk=32), np.float32)
    test_shapes = np.asarray(evaluate_batch(rig, test, chunk=32), np.float32)
    basis, picked = pbs_basis(neutral, train_shapes, args.basis)
    skin = model.part_mask(SKIN)
    return dict(
        model=model,
        rig=rig,
        neutral=neutral,
        faces=faces,
        active=active,
        parts=parts,
        layout=layout,
        layout_s=layout_s,
        capture=capture,
        capture_train=capture_train,
        train=train,
        test=test,
        train_shapes=train_shapes,
        test_shapes=test_shapes,
        basis=basis,
        picked=picked,
        skin=skin,
        handle_region=skin if args.handles_on == "skin" else active,
        graph=_graph(args, model, neutral, faces),
    )


def _graph(args, model, neutral, faces):
    """The masks' edge graph (--graph)."""
    if args.graph == "mesh":
        return edge_graph(neutral, faces)
    graph = bridged_edge_graph(neutral, faces)
    if args.graph == "attached":
        graph = attached_edge_graph(
            graph,
            neutral,
            model.part_mask(args.attach, "--attach"),
            model.part_mask(args.attach_onto, "--attach-onto"),
        )
    return graph


def _training_set(args, head):
    region = head["handle_region"]
    pool = np.random.default_rng([0, 3]).choice(
        np.flatnonzero(region), min(POOL_SIZE, int(region.sum())), replace=False
    )
    distances = seed_distances(head["layout"], head["graph"])
    return build_pbs_training_set(
        head["neutral"], head["train_shapes"], head["layout"], head["basis"], distances, pool
    ), distances


def _region_errors(head, error_mm: np.ndarray) -> dict:
    """Mean per-vertex error (mm) over the vertices of each of ``REGIONS``, and each region's
    share of the whole-head mean (its error summed over its vertices / all vertices)."""
    n = error_mm.shape[1]
    out = {}
    for region, parts in REGIONS.items():
        index = np.flatnonzero(head["model"].part_mask(parts))
        part = error_mm[:, index]
        out[region] = {
            "mean_mm": float(part.mean()),
            "share_of_mean_mm": float(part.sum(axis=1).mean() / n),
            "vertices": int(len(index)),
        }
    return out


def _handle_reach(head, handle_distance: np.ndarray) -> dict:
    """Per region of ``REGIONS``: how far the patches seeded there lie from Table 5's nearest
    handle along the masks' graph (cm; median, max), and the fraction within the masks' radius
    and within their reach (the distance where the clamped mask becomes exactly 0)."""
    seeds = np.asarray(head["layout"].seeds)
    nearest = handle_distance.min(axis=1)  # (P,)
    reach = float(influence_reach(EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP))
    out = {"radius_cm": EVAL_RADIUS_CM, "reach_cm": reach, "regions": {}}
    for region, parts in REGIONS.items():
        inside = head["model"].part_mask(parts)[seeds]
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


def _check_graph(args, folder: Path) -> None:
    """Refuse to resume or evaluate a model trained with other --handles-on / --graph options
    (``canrig_jax.canrig.check_pbs_training_matches``)."""
    check_pbs_training_matches(
        folder,
        handles_on=args.handles_on,
        graph=args.graph,
        attach=args.attach,
        attach_onto=args.attach_onto,
    )


def _train(args, argv, head):
    options = PBSTrainOptions(
        model=args.train,
        steps=args.steps,
        max_minutes=args.minutes,
        decay_start=args.decay_start,
        decay_steps=args.decay_steps,
        learning_rate=args.learning_rate,
        local_prior=args.local_prior,
    )
    data, _ = _training_set(args, head)
    folder = args.out / MODELS_DIR / (args.train + args.tag)
    _check_graph(args, folder)
    folder.mkdir(parents=True, exist_ok=True)
    scale = float(np.abs(head["train_shapes"] - head["neutral"]).max())
    _, step, seconds, history = train_pbs(
        data,
        options,
        checkpoint=folder / "checkpoint.eqx",
        displacement_scale=scale,
        progress=not args.no_progress,
    )
    save_json(
        folder / "train.json",
        {
            "model": args.train,
            "steps": step,
            "train_minutes": seconds / 60,
            "options": options.to_dict(),
            "graph": args.graph,
            **(
                {"attach": args.attach, "attach_onto": args.attach_onto}
                if args.graph == "attached"
                else {}
            ),
            "handles_on": args.handles_on,
            "history": history,
            "provenance": provenance(experiment_command(__file__, argv)),
        },
    )
    print(f"{args.train}: {step} steps in {seconds / 60:.1f} min")


DIALOGUE_HANDLES, DIALOGUE_RADIUS_CM, DIALOGUE_FALLOFF = 60, 1.5, 3.0
DIALOGUE_REACH_CM = float(influence_reach(DIALOGUE_RADIUS_CM, DIALOGUE_FALLOFF, CLAMP))
"""Beyond this distance from a mouth handle its clamped mask is exactly 0."""
MOUTH_THRESHOLD_CM = 0.3  # as experiments/canrig_workflows.py


SWEEP_HEADER = "Table 6, a variant: the number of mouth handles"


def _table6_sweep(args, command, head):
    """``--table6-sweep``: Table 6 with each number of mouth handles (the 140 still ones
    unchanged), merged into OUT's results.json and table.md."""
    if min(args.table6_sweep) < 1:
        raise ValueError(f"--table6-sweep: expected counts >= 1, got {args.table6_sweep}")
    data, distances = _training_set(args, head)
    clips = _dialogue_clips(head, args)
    sweep = {}
    for count in args.table6_sweep:
        table6, _ = _table6(args, head, data, distances, n_mouth=count, clips=clips)
        sweep[str(count)] = {
            "reach_floor_mm": table6["reach_floor_mm"],
            "unreached_region_vertices": table6["unreached_region_vertices"],
            **{k: v["mouth_difference_mm"] for k, v in table6["methods"].items()},
            "per_patch_rest_of_face_change_max_mm": table6["methods"]
            .get("per_patch", {})
            .get("rest_of_face_change_mm"),
        }
    path = args.out / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    results["table6_handle_sweep"] = {
        "mouth_difference_mm": sweep,
        "protocol": "Table 6's protocol with K mouth handles (farthest points among the same "
        "candidates) instead of 60; the baselines get the same K plus the 140 still handles; "
        "reach_floor_mm: the mouth difference of the region's vertices no moved handle's "
        "clamped mask reaches (they keep the source frame in any CANRig-PBS result)",
        "provenance": provenance(command),
    }
    save_json(path, results)
    methods = [
        k
        for k in ("per_patch", "shape_transformer", "gbs_19", "gbs_ict_53")
        if k in sweep[str(args.table6_sweep[0])]
    ]
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
    table = args.out / "table.md"
    text = table.read_text() if table.exists() else ""
    text = text.split(SWEEP_HEADER)[0].rstrip("\n") + "\n\n" + "\n".join(lines) + "\n"
    save_text(table, text)
    record_command(args.out, command)
    print("\n".join(lines))


def _dense_reference_ms(head, handles):
    """One dense per-vertex forward pass (an untrained ShapePreservingCANRig, the encoder
    sizes of PBSTrainOptions) on all vertices at these handles: the timing reference."""
    o = PBSTrainOptions()
    neutral = head["neutral"]
    net = ShapePreservingCANRig(
        neutral,
        n_heads=o.n_heads,
        latent=o.latent,
        width=o.width,
        n_layers=o.n_layers,
        fourier=o.fourier,
        key=jax.random.PRNGKey(0),
    )
    # (H, V): paths from every vertex to the handles (the transpose of a bridged graph)
    distance = weighted_geodesic_distance(head["graph"].T.tocsr(), handles)
    mask = influence_mask(distance.T, EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM)
    queries = net.encode_queries(jnp.asarray(neutral))
    base = jnp.asarray(neutral)
    d = jnp.asarray(head["test_shapes"][0][handles] - neutral[handles])
    index = jnp.asarray(handles)
    call = eqx.filter_jit(lambda net, q, base, m, d: net(q, base, base[index], base[index], d, m))
    return median_ms(lambda: call(net, queries, base, mask, d))


def _dialogue_clips(head, args):
    """Table 6's source (capture frames 90..) and target (135..) clips on the whole head (45
    frames each, 6 with ``--quick``), the mouth mask (N,), the mouth patches (P,) and the
    evaluated mouth region (N,) (see ``_table6``)."""
    n = 6 if args.quick else 45
    layout, rig, capture = head["layout"], head["rig"], head["capture"]
    source = np.asarray(evaluate_batch(rig, capture[90 : 90 + n], chunk=16), np.float32)
    target = np.asarray(evaluate_batch(rig, capture[135 : 135 + n], chunk=16), np.float32)
    mouth = expression_region(rig, threshold=MOUTH_THRESHOLD_CM)
    mouth_patch = mouth[np.asarray(layout.seeds)]
    return source, target, mouth, mouth_patch, layout.covered_by(mouth_patch)


def _mouth_handles(head, distances, mouth, mouth_patch, count: int):
    """``count`` mouth handles: farthest points among the mouth vertices from which no patch
    seeded outside the mouth is within the clamped mask's reach."""
    outside_seed_distance = distances[~mouth_patch].min(axis=0)  # (N,) to the nearest
    candidates = np.flatnonzero(mouth & (outside_seed_distance > DIALOGUE_REACH_CM))
    return candidates[farthest_point_vertices(head["neutral"][candidates], count)]


def _table6(args, head, data, distances, n_mouth: int = DIALOGUE_HANDLES, clips=None):
    """Dialogue replacement (Table 6) on the whole head for the trained models and GBS.

    The mouth mask is ``expression_region`` of the whole-head rig (threshold 3 mm, as the
    workflows experiment); PBS moves whole patches, so the evaluated mouth region is every
    vertex a patch seeded in the mouth mask covers, and the rest of the face is the
    complement. CANRig-PBS: 60 handles in the mouth where no patch seeded outside it is
    within the masks' reach, moved to the target frame, base = the source frame. Shape
    Transformer and GBS (no base shape): the source frame is first inverted from 200 handles
    (those 60 + 140 geodesic farthest points off the mouth region), then the 60 move.
    ``clips``: ``_dialogue_clips`` if the caller has them."""
    neutral, rig = head["neutral"], head["rig"]
    if clips is None:
        clips = _dialogue_clips(head, args)
    source, target, mouth, mouth_patch, region = clips
    n = len(source)
    mouth_handles = _mouth_handles(head, distances, mouth, mouth_patch, n_mouth)
    off = np.flatnonzero(~region & head["skin"])
    still = off[farthest_point_vertices(neutral[off], 200 - DIALOGUE_HANDLES)]
    all_handles = np.concatenate([mouth_handles, still])
    moved = np.arange(len(all_handles)) < n_mouth

    def error(a, b, where):
        return float((np.linalg.norm(a - b, axis=-1) * CM_TO_MM)[:, where].mean())

    methods, outputs = {}, {}
    for name in ("per_patch", "shape_transformer"):
        checkpoint = args.out / MODELS_DIR / name / "checkpoint.eqx"
        if not checkpoint.exists():
            continue
        net, _ = load_pbs_model(checkpoint, neutral, args.patches, len(head["basis"]))
        if name == "per_patch":  # base = each source frame, the mouth handles move
            index, bases = mouth_handles, source
            inverted_targets, edited_targets = source, target
        else:  # no base: from the neutral, every handle at the frame (the mouth's edited)
            index, bases = all_handles, neutral
            inverted_targets, edited_targets = source, source.copy()
            edited_targets[:, mouth_handles] = target[:, mouth_handles]
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
        outputs[name] = edited
        methods[name] = {
            "rig_inversion_mm": float(
                (np.linalg.norm(inverted - source, axis=-1) * CM_TO_MM).max()
                if name == "per_patch"
                else (np.linalg.norm(inverted - source, axis=-1) * CM_TO_MM).mean()
            ),
            "mouth_difference_mm": error(edited, target, region),
            "rest_of_face_change_mm": float(
                (np.linalg.norm(edited - source, axis=-1) * CM_TO_MM)[:, ~region].max()
                if name == "per_patch"
                else error(edited, source, ~region)
            ),
        }
    for name, basis in (("gbs_19", head["basis"]), ("gbs_ict_53", np.asarray(rig.deltas))):
        inverted, edited = global_blendshape_dialogue(
            basis, neutral, source, target, all_handles, moved
        )
        inverted, edited = np.asarray(inverted), np.asarray(edited)
        outputs[name] = edited
        methods[name] = {
            "rig_inversion_mm": error(inverted, source, slice(None)),
            "mouth_difference_mm": error(edited, target, region),
            "rest_of_face_change_mm": error(edited, source, ~region),
        }
    floor_mm, unreached = reach_floor(
        head["layout"], distances, mouth_handles, source, target, region, reach_cm=DIALOGUE_REACH_CM
    )
    table6 = {
        "methods": methods,
        "mouth_handles": int(n_mouth),
        "reach_floor_mm": floor_mm,
        "unreached_region_vertices": unreached,
        "no_edit_mouth_difference_mm": error(source, target, region),
        "frames": {"source": [90, 89 + n], "target": [135, 134 + n]},
        "mouth_region_vertices": int(region.sum()),
        "protocol": "source capture frames 90-134, target 135-179; CANRig-PBS inversion and "
        "rest of face are maxima, the others means; mouth region: every vertex covered by "
        f"a patch seeded in expression_region(threshold={MOUTH_THRESHOLD_CM} cm) "
        f"({int(region.sum())} vertices)",
    }
    print(f"table 6: {methods}")
    return table6, {"source": source, "target": target, "outputs": outputs, "region": region}


def main(argv=None):
    args = _parser().parse_args(argv)
    if args.quick:
        args.patches, args.n_random = 60, 60
    command = experiment_command(__file__, argv)
    head = _whole_head(args)
    head["out"] = args.out
    if args.train is not None:
        return _train(args, argv, head)
    if args.table6_sweep is not None:
        return _table6_sweep(args, command, head)
    model, neutral, faces = head["model"], head["neutral"], head["faces"]
    layout, layout_s, parts = head["layout"], head["layout_s"], head["parts"]
    sizes = np.array([len(v) for v in layout.patch_vertices()])
    capture, capture_train = head["capture"], head["capture_train"]
    test, test_shapes = head["test"], head["test_shapes"]
    basis, picked, active = head["basis"], head["picked"], head["active"]

    fitted = fit_pbs(layout, neutral, basis, test_shapes)
    represented = np.asarray(pbs_shape(layout, neutral, basis, fitted))
    error = np.linalg.norm(represented - test_shapes, axis=-1) * CM_TO_MM  # (T, V) mm
    face = slice(*model.part_vertex_range[0])
    pbs = {
        "patches": args.patches,
        "basis": args.basis,
        "rings": args.rings,
        "parts": parts,
        "active_vertices": int(active.sum()),
        "patch_size": {
            "min": int(sizes.min()),
            "median": float(np.median(sizes)),
            "max": int(sizes.max()),
        },
        "max_patches_per_vertex": int(layout.vertex_patches.shape[1]),
        "basis_training_index": picked.tolist(),
        "fit_mean_mm": float(error.mean()),
        "fit_p95_mm": float(np.percentile(error, 95)),
        "fit_face_mean_mm": float(error[:, face].mean()),
        "fit_max_mm": float(error.max()),
        "layout_seconds": layout_s,
    }

    # Table 5, GBS rows: handles by geodesic farthest points on the skin (Face, Head and
    # Neck; --handles-on moving: on every part that moves), reconstruction relative to the
    # neutral (no base shape), error over every vertex
    region = head["handle_region"]
    region_index = np.flatnonzero(region)
    local = np.full(len(neutral), -1)
    local[region_index] = np.arange(len(region_index))
    region_faces = local[faces[region[faces].all(axis=1)]]
    graph = edge_graph(neutral[region_index], region_faces)
    handles = region_index[
        farthest_point_vertices(neutral[region_index], args.handles, graph=graph)
    ]
    offsets = test_shapes - neutral
    table5 = {}
    for name, shapes in (("gbs_pbs_basis", basis), ("gbs_ict_53", np.asarray(model.deltas))):
        weights = global_blendshape_fit(shapes, handles, offsets[:, handles])
        predicted = neutral + np.einsum("tb,bnk->tnk", np.asarray(weights), shapes)
        error_mm = np.linalg.norm(predicted - test_shapes, axis=-1) * CM_TO_MM
        per_shape = error_mm.mean(axis=1)
        table5[name] = {
            "mean_mm": float(per_shape.mean()),
            "std_mm": float(per_shape.std()),
            "train_minutes": 0.0,
            "basis_size": int(len(shapes)),
            "regions": _region_errors(head, error_mm),
        }
    no_motion_mm = np.linalg.norm(offsets, axis=-1) * CM_TO_MM
    no_motion = no_motion_mm.mean(axis=1)
    table5["no_motion"] = {
        "mean_mm": float(no_motion.mean()),
        "std_mm": float(no_motion.std()),
        "train_minutes": 0.0,
        "regions": _region_errors(head, no_motion_mm),
    }

    # Table 5 and Figure 8, the trained rows: the same handles, base = the neutral
    data, distances = _training_set(args, head)
    handle_distance = jnp.asarray(distances[:, handles])
    reach = _handle_reach(head, distances[:, handles])
    neutral_j, test_j = jnp.asarray(neutral), jnp.asarray(test_shapes)

    def reconstruct(net, index, distance, targets, queries=None):
        return pbs_reconstruct(
            net,
            data,
            index,
            distance,
            neutral_j,
            targets,
            EVAL_RADIUS_CM,
            EVAL_FALLOFF_PER_CM,
            queries,
        )

    def evaluate(folder):
        checkpoint = args.out / MODELS_DIR / folder / "checkpoint.eqx"
        if not checkpoint.exists():
            print(f"{folder}: no checkpoint at {checkpoint}, row skipped")
            return None, None
        _check_graph(args, checkpoint.parent)
        net, state = load_pbs_model(checkpoint, neutral, args.patches, len(basis))
        shapes = np.asarray(reconstruct(net, jnp.asarray(handles), handle_distance, test_j))
        error_mm = np.linalg.norm(shapes - test_shapes, axis=-1) * CM_TO_MM
        per_shape = error_mm.mean(axis=1)
        row = {
            "mean_mm": float(per_shape.mean()),
            "std_mm": float(per_shape.std()),
            "train_minutes": float(state["seconds"] / 60),
            "steps": int(state["step"]),
            "parameters": parameter_count(net),
            "regions": _region_errors(head, error_mm),
        }
        print(f"{folder}: {row}")
        return net, row

    trained, figure8, forward, nets = {}, {}, {}, {}
    h200, d200 = jnp.asarray(handles[:200]), handle_distance[:, :200]
    for name in TABLE5_MODELS:
        net, row = evaluate(name)
        if row is not None:
            trained[name] = row
            nets[name] = net
            if getattr(net, "local_prior", False):
                row["local_prior_ridge"] = float(jnp.exp(net.log_ridge))
            # one whole-head forward pass at 200 handles
            # (patch queries cached once per mesh, as the per-vertex reference's queries)
            queries = net.encode_patches(data.seeds)
            forward[name] = median_ms(
                lambda net=net, queries=queries: reconstruct(net, h200, d200, test_j[:1], queries)
            )
    # the local fit alone (no network): CANRig-PBS's local prior at its trained ridge, or at
    # the default initial one when the per_patch model has no prior
    prior_net = nets.get("per_patch")
    ridge = (
        float(jnp.exp(prior_net.log_ridge))
        if prior_net is not None and prior_net.local_prior
        else LOCAL_FIT_RIDGE
    )
    mask = influence_mask(handle_distance, EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP)
    local_weights = local_pbs_fit(basis[:, handles], offsets[:, handles], mask, ridge)
    error_mm = (
        np.stack(
            [
                np.linalg.norm(np.asarray(pbs_shape(layout, neutral, basis, w)) - shape, axis=-1)
                for w, shape in zip(np.asarray(local_weights), test_shapes, strict=True)
            ]
        )
        * CM_TO_MM
    )
    table5["local_fit"] = {
        "mean_mm": float(error_mm.mean(axis=1).mean()),
        "std_mm": float(error_mm.mean(axis=1).std()),
        "train_minutes": 0.0,
        "ridge": ridge,
        "regions": _region_errors(head, error_mm),
    }
    for name in PBS_VARIANTS:
        _, row = evaluate(name + FIGURE8_TAG)
        if row is not None:
            figure8[name] = row
    table5.update(trained)

    # gather form against the sparse matrix product, one shape
    w_layout = layout.matrix()
    weights0 = jnp.asarray(fitted[0])
    basis_j = jnp.asarray(basis)
    neutral_j = jnp.asarray(neutral)
    gather_ms = median_ms(lambda: pbs_shape(layout, neutral_j, basis_j, weights0))

    def sparse():
        per_vertex = w_layout @ np.asarray(weights0)  # (N, B)
        return neutral + np.einsum("nb,bnk->nk", per_vertex, basis)

    sparse_ms = median_ms(sparse)
    timing = {"pbs_shape_gather_ms": gather_ms, "pbs_shape_scipy_sparse_ms": sparse_ms}
    print(
        f"PBS fit: mean {pbs['fit_mean_mm']:.4f} mm, p95 {pbs['fit_p95_mm']:.4f} mm; "
        f"gather {gather_ms:.2f} ms, scipy.sparse {sparse_ms:.2f} ms"
    )

    forward["dense_per_vertex_reference"] = _dense_reference_ms(head, handles[:200])
    table6, dialogue_run = _table6(args, head, data, distances) if trained else ({}, None)
    results = {
        "pbs": pbs,
        "table5": table5,
        "figure8": figure8,
        # the schema: table6 -> method -> {rig_inversion_mm, mouth_difference_mm,
        # rest_of_face_change_mm}; the handles, reach floor, frames and protocol beside it
        "table6": table6.get("methods", {}),
        "table6_setup": {k: v for k, v in table6.items() if k != "methods"},
        "table5_reach": reach,
        "forward_ms_whole_head": forward.get("per_patch"),
        "forward_ms": forward,
        "timing": timing,
        "protocol": {
            "shapes": "whole ICT head (26,719 vertices): the ict-quartic rig on the face part "
            "plus ICT's expression deltas elsewhere (autorig.head_rig)",
            "train": f"capture frames 0-{len(capture_train) - 1} + {args.n_random} random poses",
            "test": f"capture frames {len(capture_train)}-{len(capture) - 1} + 100 random "
            "poses (held_out_poses)",
            "handles": f"{args.handles} geodesic farthest points on "
            + (
                f"the skin ({', '.join(SKIN)})"
                if args.handles_on == "skin"
                else "every moving part"
            )
            + f"; training handles drawn from the same region ({args.handles_on})",
            "masks": f"CANRig-PBS: radius {EVAL_RADIUS_CM} cm, falloff {EVAL_FALLOFF_PER_CM}/cm, "
            "evaluated at each patch's seed vertex (geodesic distance on the whole head, "
            + {
                "bridged": "bridged: every floating part's vertices step to their nearest "
                "skin-component vertex)",
                "mesh": "mesh edges only: teeth, gums, eyelashes out of reach)",
                "attached": "bridged, and the vertices of "
                + ", ".join(args.attach)
                + " one-way exits onto their nearest vertex of "
                + ", ".join(args.attach_onto)
                + ", straight through the mouth cavity: mesh.attached_edge_graph)",
            }[args.graph],
            "forward": "one call at 200 handles (ms, median): the whole-head shape from the "
            "handle displacements; dense_per_vertex_reference: an untrained per-vertex "
            "ShapePreservingCANRig with the same encoder on all 26,719 vertices, dense masks",
        },
        "provenance": provenance(command),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    rows = [
        "| method | mean (std) mm | training minutes | steps | parameters |",
        "|---|---|---|---|---|",
    ]
    labels = {
        "no_motion": "no motion (the neutral)",
        "gbs_pbs_basis": f"GBS, the {len(basis)} PBS offsets",
        "gbs_ict_53": "GBS, ICT's 53 expressions",
        "shape_transformer": "Shape Transformer (PBS output)",
        "local_fit": "local PBS fit alone (CANRig-PBS's local prior without the network)",
        "per_patch": "CANRig-PBS (per-patch MLPs)"
        + (" + local prior" if "local_prior_ridge" in table5.get("per_patch", {}) else ""),
    }
    for key, label in labels.items():
        if key not in table5:
            continue
        row = table5[key]
        rows.append(
            f"| {label} | {row['mean_mm']:.3f} ({row['std_mm']:.3f}) | "
            f"{row['train_minutes']:.1f} | {row.get('steps', '-')} | "
            f"{row.get('parameters', '-')} |"
        )
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
    reach_rows = [
        "| region | patches | nearest handle median (max) cm | within radius | within reach |",
        "|---|---|---|---|---|",
    ] + [
        f"| {k} | {v['patches']} | {v['nearest_handle_median_cm']:.2f} "
        f"({v['nearest_handle_max_cm']:.2f}) | {v['within_radius']:.2f} | "
        f"{v['within_reach']:.2f} |"
        for k, v in reach["regions"].items()
        if v["patches"]
    ]
    fig8 = [
        "| Figure 8 variant | held-out mean (std) mm | steps | parameters |",
        "|---|---|---|---|",
    ] + [
        f"| {k} | {v['mean_mm']:.3f} ({v['std_mm']:.3f}) | {v['steps']} | {v['parameters']} |"
        for k, v in figure8.items()
    ]
    t6 = [
        "| method | rig inversion mm | mouth difference mm | rest of face change mm |",
        "|---|---|---|---|",
    ] + [
        f"| {k} | {v['rig_inversion_mm']:.3f} | {v['mouth_difference_mm']:.3f} | "
        f"{v['rest_of_face_change_mm']:.3f} |"
        for k, v in table6.get("methods", {}).items()
    ]
    fwd = ["| forward pass, 200 handles, whole head | ms |", "|---|---|"] + [
        f"| {k} | {v:.1f} |" for k, v in forward.items()
    ]
    text = "\n".join(
        [
            "# Patch blendshapes on the whole ICT head (issue 18)",
            "",
            f"Command: `{command}`",
            "",
            f"PBS: {args.patches} patches over {pbs['active_vertices']} vertices "
            f"({', '.join(parts)}), {args.rings} rings of overlap, basis = neutral + "
            f"{len(basis)} extreme training shapes.",
            "",
            "| PBS fit of held-out shapes | mean mm | p95 mm | face mean mm | max mm |",
            "|---|---|---|---|---|",
            f"| per-patch least squares | {pbs['fit_mean_mm']:.4f} | {pbs['fit_p95_mm']:.4f} | "
            f"{pbs['fit_face_mean_mm']:.4f} | {pbs['fit_max_mm']:.3f} |",
            "",
            f"Table 5 ({args.handles} handles, reconstruction relative to the neutral, "
            f"{len(test)} held-out shapes):",
            "",
            *rows,
            "",
            "Table 5 by region: mean error over the region's vertices, in brackets its share "
            "of the whole-head mean (mm; the shares sum to the mean, the eyeballs do not move). "
            "mouth_interior: "
            + ", ".join(REGIONS["mouth_interior"])
            + "; eye_parts: the eye sockets, lacrimal fluid, eye blend, eye occlusion and "
            "eyelashes.",
            "",
            *by_region,
            "",
            f"Handle reach (--graph {args.graph}): each region's patches, the distance from "
            "the seed to Table 5's nearest handle along the masks' graph, the fraction within "
            f"the radius ({reach['radius_cm']:.1f} cm) and within the clamped mask's reach "
            f"({reach['reach_cm']:.2f} cm; beyond it no handle moves the patch).",
            "",
            *reach_rows,
            "",
            f"W_layout application: gather form {gather_ms:.2f} ms, "
            f"scipy.sparse {sparse_ms:.2f} ms (one shape).",
            "",
            *(
                [
                    "Figure 8 (each variant 1,000 steps of the same 2,000-step cosine "
                    "schedule; Table 5's protocol):",
                    "",
                    *fig8,
                ]
                if figure8
                else [
                    "Figure 8: no variant trained in this folder "
                    f"(`--train NAME --tag {FIGURE8_TAG}`)."
                ]
            ),
            "",
            "Table 6 (dialogue replacement on the whole head; " + table6.get("protocol", "") + "):",
            "",
            *t6,
            "",
            *(
                [
                    f"Reach floor of CANRig-PBS's mouth difference: {table6['reach_floor_mm']:.3f}"
                    f" mm ({table6['unreached_region_vertices']} of the region's vertices lie "
                    "beyond every moved handle's clamped mask and keep the source frame).",
                    "",
                ]
                if "reach_floor_mm" in table6
                else []
            ),
            *fwd,
            "",
        ]
    )
    save_text(args.out / "table.md", text)
    trained_commands = [
        json.loads((args.out / MODELS_DIR / name / "train.json").read_text())["provenance"][
            "command"
        ]
        for name in [*trained, *(k + FIGURE8_TAG for k in figure8)]
        if (args.out / MODELS_DIR / name / "train.json").exists()
    ]
    save_text(
        args.out / "COMMAND",
        "# training, one model each (resumable; the same command continues a run)\n"
        + "".join(c + "\n" for c in trained_commands)
        + (
            "# (per_patch_fig8 is the per_patch run's checkpoint at step 1,000, copied while it\n"
            "# trained; its command reproduces it bit-identically. Its 21 MB checkpoint is not\n"
            "# committed: run that command before the evaluation to regenerate Figure 8's row.)\n"
            if "per_patch" in figure8
            else ""
        )
        + "# evaluation (Table 5, Figure 8, Table 6, timing, figures)\n"
        + command
        + "\n",
    )
    if "per_patch" in trained:
        _figure_edit(head, data, distances, handles[:200], args.out / "whole_head_edit.png")
    if dialogue_run is not None:
        _figure_dialogue(head, dialogue_run, args.out / "table6_error.png")

    cell = np.asarray(layout.cell).astype(float)
    shuffled = np.random.default_rng(0).permutation(args.patches)
    colour = np.where(cell >= 0, shuffled[np.maximum(cell, 0).astype(int)], 0)
    fig, axes = plt.subplots(1, 2, figsize=(9, 5))
    for ax, view in zip(axes, ("front", "side"), strict=True):
        plot_vertex_scalar(
            ax,
            neutral,
            faces,
            colour,
            vmin=0,
            vmax=args.patches,
            cmap="tab20",
            view=view,
            title=f"{args.patches} patches ({view})",
        )
    save_figure(fig, args.out / "patch_layout.png")
    fig, ax = plt.subplots(figsize=(5, 5))
    plot_vertex_scalar(
        ax,
        neutral,
        faces,
        error.mean(axis=0),
        vmin=0,
        vmax=0.2,
        title="PBS fit, mean held-out error (0-0.2 mm)",
    )
    save_figure(fig, args.out / "pbs_error.png")


def _figure_edit(head, data, distances, handles, path):
    """Figure: the per-patch model at 200 handles on the held-out shape that moves most."""
    neutral, faces, test = head["neutral"], head["faces"], head["test_shapes"]
    pick = int(np.argmax(np.linalg.norm(test - neutral, axis=-1).mean(axis=1)))
    checkpoint = head["out"] / MODELS_DIR / "per_patch" / "checkpoint.eqx"
    net, _ = load_pbs_model(checkpoint, neutral, data.weights.shape[1], data.weights.shape[2])
    out = np.asarray(
        pbs_reconstruct(
            net,
            data,
            jnp.asarray(handles),
            jnp.asarray(distances[:, handles]),
            jnp.asarray(neutral),
            jnp.asarray(test[pick : pick + 1]),
            EVAL_RADIUS_CM,
            EVAL_FALLOFF_PER_CM,
        )[0]
    )
    fig, axes = plt.subplots(1, 3, figsize=(13, 5))
    panels = (
        (test[pick], np.linalg.norm(test[pick] - neutral, axis=-1) * CM_TO_MM, 10, "target motion"),
        (out, np.linalg.norm(out - neutral, axis=-1) * CM_TO_MM, 10, "CANRig-PBS motion"),
        (out, np.linalg.norm(out - test[pick], axis=-1) * CM_TO_MM, 3, "error"),
    )
    for ax, (mesh, value, top, title) in zip(axes, panels, strict=True):
        plot_vertex_scalar(ax, mesh, faces, value, vmin=0, vmax=top, title=f"{title} (0-{top} mm)")
    axes[0].scatter(*neutral[handles][:, :2].T, s=2, c="k")
    fig.suptitle(f"200 handles, whole head (26,719 vertices), held-out shape {pick}")
    save_figure(fig, path)


def _figure_dialogue(head, run, path):
    """Figure 12 analog: per method, the distance to the target frame in the middle of the
    clip (mm) and the mouth region."""
    faces = head["faces"]
    frame = len(run["source"]) // 2
    names = list(run["outputs"])
    fig, axes = plt.subplots(1, len(names) + 1, figsize=(4 * (len(names) + 1), 4.5))
    plot_vertex_scalar(
        axes[0],
        run["source"][frame],
        faces,
        run["region"].astype(float),
        vmin=0,
        vmax=1,
        title="mouth region",
    )
    for ax, name in zip(axes[1:], names, strict=True):
        edited = run["outputs"][name][frame]
        distance = np.linalg.norm(edited - run["target"][frame], axis=-1) * CM_TO_MM
        plot_vertex_scalar(ax, edited, faces, distance, vmin=0, vmax=5, title=f"{name} (0-5 mm)")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
