"""The production solver's terms and sparse targets on the ict-quartic rig and the MakeHuman
hm08 head (evaluation only), with the noisy Live Link take.

    python experiments/inverse_rig_production.py --out experiments/results/inverse_rig

The protocol, fixed before measuring:

- rigs, take and noise as ``inverse_rig.py``: ict-quartic (cm) and ``makehuman_quartic_rig``
  (dm), the 180-frame Live Link Face take (60 fps) on each rig's names (``missing="zero"``),
  Gaussian noise of variance ``NOISE_VARIANCE_CM2`` = 0.03 cm^2 per coordinate (seed 0) on the
  clean meshes, or on the clean points for sparse targets;
- method: converged ``inverse.QuarticNewton`` (its defaults), frames independent, at
  alpha = ``ALPHA_CM2`` = 1.0 cm^2 for the dense mesh (``inverse_rig_exclusions.py``'s fixed
  choice), converted to the rig's units (divided by (cm per unit)^2).

``sparse_points``: the MediaPipe canonical face (468 points, cm) converted to the head's
units and bound to it by ``mesh.bind_points`` (trimmed-ICP similarity onto the skin: ICT's
face part, MakeHuman's ``body`` group; then closest surface points, barycentric): no
correspondence is given. Subsets of 20, 50 and 100 landmarks by farthest-point sampling on the
canonical face (``mesh.farthest_point_vertices`` from landmark 1, the nose tip), all 468, and
the dense mesh. The targets are the bound points of the clean meshes plus noise. alpha is
scaled with the number of points (alpha_dense * N / V: the same L1 weight per observed
point). Metrics: the mean per-frame RMSE (mm) of the *whole* mesh reconstructed from the
solved weights against the clean meshes, its ratio to the dense solve's, the cardinality, ms
per frame (one timed batched run after compilation; the machine's two cores were shared),
and the binding's RMS distance (mm) of the moved landmarks to the head. Variants beside it:
the dense alpha unchanged for every N, and the same N points without noise.

``production`` (ict-quartic only): each term of ``inverse.Constrained`` alone, at fixed
values (``TERMS``), then all together; the temporal term runs in a warm-started
``inverse.Stream`` (previous frame), the others batched. Metrics: RMSE and p95 (mm),
cardinality, ``roughness`` (sum of squared second differences of the weights), asymmetry (mean
abs(w_left - w_right) over ``left_right_pairs``), frames with a cancel pair
(``rig.exclusive_pairs``) both active (weights > ``CARDINALITY_TOL``) and ms per frame.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from canrig_jax import inverse
from canrig_jax._io import update_results
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.data import load_livelinkface, load_mediapipe_face
from canrig_jax.inverse import CARDINALITY_TOL, both_active, roughness, summarize
from canrig_jax.mesh import bind_points, farthest_point_vertices
from canrig_jax.papers.inverse_rig import time_batched
from canrig_jax.rig import (
    UNIT_IN_CM,
    evaluate_batch,
    exclusive_pairs,
    ict_quartic_rig,
    makehuman_quartic_rig,
)
from canrig_jax.watchdog import run_watched

NOISE_VARIANCE_CM2 = 0.03
ALPHA_CM2 = 1.0
POINT_COUNTS = (20, 50, 100, 468)
NOSE_TIP = 1  # MediaPipe's landmark 1
ICT_FACE_VERTICES = 9409  # ict-facekit README: the face part is vertices 0..9408
TERMS = {"l2_weight": 1.0, "tie_weight": 10.0, "temporal_weight": 10.0}  # cm^2, like alpha


def _take(capture, rig, quick):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        take = capture.weights_for(rig.names, missing="zero")
    return take[:20] if quick else take


def _skin_triangles(name, rig, data_dir):
    faces = np.asarray(rig.faces)
    if name == "ict":
        return np.all(faces < ICT_FACE_VERTICES, axis=1)
    from canrig_jax.data import data_file, read_arrays  # the hm08 face groups

    groups = read_arrays(data_file("makehuman/hm08_face.npz", data_dir), ("face_group",))
    group = groups["face_group"]
    if group.shape[0] != faces.shape[0]:
        raise ValueError("makehuman: face groups do not match the rig's faces")
    return group == "body"


def sparse_points(name, rig, take, rng, args):
    """{points: row} for one head (see the module docstring)."""
    scale = UNIT_IN_CM[rig.units]
    landmarks = load_mediapipe_face(args.data_dir)
    order = farthest_point_vertices(landmarks.neutral, 468, start=NOSE_TIP)
    binding, fit = bind_points(
        landmarks.neutral / scale,
        np.asarray(rig.neutral),
        np.asarray(rig.faces),
        target_triangles=_skin_triangles(name, rig, args.data_dir),
    )
    clean = np.asarray(evaluate_batch(rig, take))
    sigma = np.sqrt(NOISE_VARIANCE_CM2) / scale
    dense_alpha = ALPHA_CM2 / scale**2
    corners = np.asarray(rig.faces)[binding.triangle]
    rows = {}
    for count in (*POINT_COUNTS, "dense"):
        if count == "dense":
            problem, targets, alpha = inverse.prepare(rig), clean, dense_alpha
        else:
            chosen = np.sort(order[:count])
            points = (binding.triangle[chosen], binding.barycentric[chosen])
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*move none of the points")
                problem = inverse.prepare(rig, points=points)
            weights = binding.barycentric[chosen]
            targets = np.einsum("tnjd,nj->tnd", clean[:, corners[chosen]], weights)
            alpha = dense_alpha * count / rig.n_vertices
        noisy = (targets + rng.normal(0.0, sigma, targets.shape)).astype(np.float32)
        method = inverse.QuarticNewton(alpha=alpha)
        seconds, solved = time_batched(problem, noisy, method, repeats=1)
        row = summarize(rig, solved, clean)
        # the variant: the dense mesh's alpha unchanged (more L1 per observed point)
        fixed = inverse.solve_sequence(problem, noisy, inverse.QuarticNewton(alpha=dense_alpha))
        rmse_fixed = summarize(rig, np.asarray(fixed.weights), clean)["rmse_mean_mm"]
        # the floor without noise: how well the points determine the pose at all
        exact = inverse.solve_sequence(problem, targets.astype(np.float32), method)
        rmse_clean = summarize(rig, np.asarray(exact.weights), clean)["rmse_mean_mm"]
        rows[str(count)] = {
            "rmse_mm_alpha_dense": rmse_fixed,
            "rmse_mm_noise_free": rmse_clean,
            "points": rig.n_vertices if count == "dense" else count,
            "rmse_mm": row["rmse_mean_mm"],
            "p95_mm": row["rmse_p95_mm"],
            "cardinality": row["cardinality"],
            "alpha": alpha,
            "ms_per_frame": seconds * 1e3,
        }
        print(f"{name} {count}: {rows[str(count)]}", flush=True)
    for row in rows.values():
        row["rmse_vs_dense"] = row["rmse_mm"] / rows["dense"]["rmse_mm"]
    binding_mm = float(np.sqrt(np.mean(binding.distance**2)) * scale * 10)
    return {"rows": rows, "binding_rms_mm": binding_mm, "fit_scale": fit.scale}


def _stream_weights(problem, noisy, method):
    stream = inverse.Stream(problem, method, warm_start=True)
    stream(noisy[0])  # compiled
    stream = inverse.Stream(problem, method, warm_start=True)
    start = time.perf_counter()
    weights = np.stack([np.asarray(stream(frame).weights) for frame in noisy])
    return (time.perf_counter() - start) / len(noisy), weights


def production(rig, take, rng, args):
    """{variant: row} of each Constrained term on ict-quartic (see the module docstring)."""
    scale = UNIT_IN_CM[rig.units]
    problem = inverse.prepare(rig)
    clean = np.asarray(evaluate_batch(rig, take))
    noise = rng.normal(0.0, np.sqrt(NOISE_VARIANCE_CM2) / scale, clean.shape)
    noisy = (clean + noise).astype(np.float32)
    base = inverse.QuarticNewton(alpha=ALPHA_CM2 / scale**2)
    pairs = tuple(exclusive_pairs(rig.names))
    ties = inverse.left_right_pairs(rig.names)
    driven = np.abs(take).max(axis=0) > 0  # shapes the capture drives: the active poses
    terms = {k: v / scale**2 for k, v in TERMS.items()}
    variants = {
        "off": base,
        "cancel_pairs": inverse.Constrained(base, exclusive=pairs),
        "symmetry": inverse.Constrained(base, ties=ties, tie_weight=terms["tie_weight"]),
        "l2": inverse.Constrained(base, l2_weight=terms["l2_weight"]),
        "temporal": inverse.Constrained(base, temporal_weight=terms["temporal_weight"]),
        "active_mask": inverse.Constrained(base, active=driven),
        "multipliers_offsets": inverse.Constrained(base, multipliers=1.1, offsets=0.01),
        "all": inverse.Constrained(base, exclusive=pairs, ties=ties, active=driven, **terms),
    }
    left, right = np.asarray(ties).T
    rows = {}
    for name, method in variants.items():
        if getattr(method, "temporal_weight", 0.0):
            seconds, weights = _stream_weights(problem, noisy, method)
        else:
            seconds, weights = time_batched(problem, noisy, method, repeats=1)
        weights = np.asarray(weights, np.float64)
        row = summarize(rig, weights, clean)
        rows[name] = {
            "rmse_mm": row["rmse_mean_mm"],
            "p95_mm": row["rmse_p95_mm"],
            "cardinality": row["cardinality"],
            "roughness": roughness(weights),
            "asymmetry": float(np.abs(weights[:, left] - weights[:, right]).mean()),
            "frames_cancel_pair_both_active": int(both_active(weights, pairs).any(1).sum()),
            "ms_per_frame": seconds * 1e3,
            "solve": "Stream(warm_start=True)" if name in ("temporal", "all") else "batched",
        }
        print(f"production {name}: {rows[name]}", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--quick", action="store_true", help="20 frames, ICT only")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    command = experiment_command(__file__, argv)
    rng = np.random.default_rng(args.seed)
    capture = load_livelinkface(args.data_dir)
    ict, _ = ict_quartic_rig(args.data_dir, progress=False)
    heads = [("ict", ict)]
    if not args.quick:
        heads.append(("makehuman", makehuman_quartic_rig(args.data_dir)[0]))
    sparse = {name: sparse_points(name, rig, _take(capture, rig, args.quick), rng, args)
              for name, rig in heads}  # fmt: skip
    rows = production(ict, _take(capture, ict, args.quick), rng, args)
    protocol = {
        "noise_variance_cm2": NOISE_VARIANCE_CM2,
        "alpha_dense_cm2": ALPHA_CM2,
        "sparse_alpha": "alpha_dense * points / vertices",
        "landmarks": "MediaPipe canonical face bound by mesh.bind_points; subsets by "
        "farthest-point sampling from landmark 1",
        "terms_cm2": TERMS,
        "active": f"weight > inverse.CARDINALITY_TOL = {CARDINALITY_TOL}",
        "frames": len(_take(capture, ict, args.quick)),
        "seed": args.seed,
        "provenance": provenance(command),
    }
    tables = sparse_table(sparse, command), production_table(rows, command)
    if args.quick:
        print("\n".join(tables))
        return sparse, rows
    args.out.mkdir(parents=True, exist_ok=True)
    update_results(args.out, "sparse_points", {**sparse, "protocol": protocol}, table=tables[0])
    update_results(args.out, "production", {"ict": rows, "protocol": protocol}, table=tables[1])
    record_command(args.out, command)
    print("\n".join(tables))
    print(f"wrote {args.out / 'results.json'} and table.md")
    return sparse, rows


def sparse_table(sparse: dict, command: str) -> str:
    text = (
        "## Sparse targets: MediaPipe landmarks bound to the head (inverse.prepare(points=))\n\n"
        "RMSE (mm) of the whole mesh from weights solved on N noisy landmarks (variance "
        f"{NOISE_VARIANCE_CM2} cm^2), against the clean take; alpha scaled with N.\n\n"
        "Variants: the dense alpha unchanged for every N, and the noise-free points (how well "
        "N points determine the pose at all).\n\n"
        "| head | points | RMSE (mm) | vs dense | p95 (mm) | cardinality | ms / frame | "
        "RMSE, dense alpha (mm) | RMSE, noise-free (mm) |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    for head, case in sparse.items():
        for count, r in case["rows"].items():
            text += (
                f"| {head} | {count} | {r['rmse_mm']:.3f} | {r['rmse_vs_dense']:.2f}x | "
                f"{r['p95_mm']:.3f} | {r['cardinality']:.1f} | {r['ms_per_frame']:.3g} | "
                f"{r['rmse_mm_alpha_dense']:.3f} | {r['rmse_mm_noise_free']:.3f} |\n"
            )
    text += "\nBinding RMS distance of the moved landmarks to the head: " + ", ".join(
        f"{h} {c['binding_rms_mm']:.2f} mm" for h, c in sparse.items()
    )
    return text + f"\n\nCommand: `{command}`\n"


def production_table(rows: dict, command: str) -> str:
    text = (
        "## Production solver terms on ict-quartic (inverse.Constrained)\n\n"
        f"Each term alone at {TERMS} (cm^2), then all together with the cancel pairs and the "
        "active mask (the shapes the capture drives); temporal: a warm-started Stream.\n\n"
        "| variant | RMSE (mm) | p95 (mm) | cardinality | roughness | asymmetry | "
        "frames with a cancel pair both active | ms / frame | solve |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    for name, r in rows.items():
        text += (
            f"| {name} | {r['rmse_mm']:.4f} | {r['p95_mm']:.4f} | {r['cardinality']:.2f} | "
            f"{r['roughness']:.3g} | {r['asymmetry']:.4f} | "
            f"{r['frames_cancel_pair_both_active']} | {r['ms_per_frame']:.3g} | {r['solve']} |\n"
        )
    return text + f"\nCommand: `{command}`\n"


if __name__ == "__main__":
    run_watched(main, "experiments/inverse_rig_production.py")
