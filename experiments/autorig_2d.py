"""2D supervision for RigAnyFace (issue 25): the differentiable rasteriser's checks and
speed, figures of a generated rig, and training with heads that have no 3D rig.

    python experiments/autorig_2d.py --out experiments/results/autorig_2d            # standard
    python experiments/autorig_2d.py --out /tmp/autorig_2d --quick                   # tests
    python experiments/autorig_2d.py --out DIR --train-only 3d_only                  # one run

Training: ICT identities, remeshed as in ``experiments/autorig.py``; the first
``--rigged-identities`` keep their 3D rig, the others are "unrigged": only renderings of their
ground-truth poses (masks, 2D displacement, 2D landmarks from ``--views`` orthographic views)
reach the training. ``3d_only``: 3D loss on the rigged heads, ``--steps`` steps.
``2d_unrigged_plus_3d``: stage 1, 2D loss on all heads (``--stage1-fraction`` of the steps),
then stage 2, 3D + 2D on the rigged heads (the rest). Evaluation: held-out identities at a
resolution never trained on (``decimate_1300``; all 96 poses, MAE in mm) and the MakeHuman
hm08 head against its person-made targets (evaluation only: nothing is trained or tuned on it).

Writes DIR/results.json, DIR/table.md, DIR/rig_poses.png, DIR/displacement_field.png,
DIR/training_loss.png and the checkpoints (a rerun resumes them).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import (
    RigAnyFaceTrainOptions,
    Supervision2DOptions,
    error_stats,
    generate_rig,
    head_inputs,
    ict_autorig_dataset,
    load_makehuman,
    padded_faces,
    sculpted_target_errors,
    shared_shape_matrix,
    train_2d,
    training_set,
)
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.render import (
    RasterSettings,
    displacement_field,
    lambert_image,
    look_at,
    rasterise,
    rasterise_hard,
    ray_cast,
    save_figure,
    silhouette,
)
from canrig_jax.watchdog import run_watched

RUNS = ("3d_only", "2d_unrigged_plus_3d")


def rasteriser_checks(data_dir, quick: bool) -> tuple[dict, tuple]:
    """Gradient vs finite differences, hard limit vs ray casting, frames per second."""
    ict = load_ict(data_dir, parts=None)
    d = decimate(ict.neutral, ict.faces, 1750)
    vertices = jnp.asarray(d.vertices, jnp.float32)
    faces = jnp.asarray(d.faces, jnp.int32)
    centre = np.asarray(vertices.mean(0))
    out = {"head": f"ICT generic head, all parts, decimated: {len(d.vertices)} v, {len(faces)} f"}
    # gradient: directional derivative along the gradient, float32, step 2e-3 cm
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=32)
    settings = RasterSettings(sigma=1.0, gamma=0.5, tile_size=4, faces_per_tile=faces.shape[0])
    weights = jnp.asarray(np.random.default_rng(0).standard_normal((2, 32, 32)), jnp.float32)

    @jax.jit
    def loss(v):
        r = rasterise(v, faces, camera, settings=settings)
        return jnp.sum(weights[0] * r.silhouette) + 0.1 * jnp.sum(
            weights[1] * r.silhouette * r.depth
        )

    grad = jax.grad(loss)(vertices)
    direction = grad / jnp.linalg.norm(grad)
    fd = (loss(vertices + 2e-3 * direction) - loss(vertices - 2e-3 * direction)) / 4e-3
    out["grad_rel_error"] = float(jnp.abs(fd - jnp.sum(grad * direction)) / jnp.abs(fd))
    out["grad_check"] = (
        "silhouette + depth loss, 32^2, sigma 1 px, gamma 0.5; directional derivative along "
        "the gradient vs central difference (2e-3 cm), float32"
    )
    # hard limit vs ray casting
    size = 48 if quick else 128
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=size)
    hard = rasterise(
        vertices, faces, camera, settings=RasterSettings.hard(faces_per_tile=faces.shape[0])
    )
    hit, depth = ray_cast(np.asarray(vertices), np.asarray(faces), camera)
    mask = np.asarray(hard.silhouette) > 0.5
    both = mask & hit
    error = np.abs(np.asarray(hard.depth)[both] - depth[both]) * 10.0  # mm
    out["hard_vs_reference_iou"] = float((mask & hit).sum() / (mask | hit).sum())
    out["hard_vs_reference_depth_mm"] = {
        "median": float(np.median(error)),
        "q99": float(np.percentile(error, 99)),
        "fraction_within_0.1mm": float(np.mean(error < 0.1)),
    }
    out["hard_reference"] = f"NumPy Moeller-Trumbore ray casting, {size}^2, perspective 30 deg"
    out["fast_path"] = fast_path_checks(vertices, faces, centre, size, quick)
    # speed at 256^2, forward + backward of a silhouette loss: the fast path and the soft one
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=256)
    default = RasterSettings()
    shifted = vertices + jnp.asarray([0.3, 0.2, 0.0])
    renders = {
        "fast": lambda v: silhouette(v, faces, camera),
        "soft": lambda v: rasterise(v, faces, camera, settings=default).silhouette,
    }
    repeats = 2 if quick else 5
    for name, render in renders.items():
        target = render(shifted)

        @jax.jit
        def step(v, render=render, target=target):
            return jax.value_and_grad(lambda v: jnp.mean((render(v) - target) ** 2))(v)

        jax.block_until_ready(step(vertices))
        times = []
        for _ in range(repeats if name == "fast" else min(repeats, 3)):
            start = time.perf_counter()
            jax.block_until_ready(step(vertices + 0.01))
            times.append(time.perf_counter() - start)
        out["fps_256" if name == "fast" else "fps_256_soft"] = float(1.0 / np.median(times))
    load = os.getloadavg()[0]
    out["fps_256_note"] = (
        "forward + backward of a silhouette loss, 256^2, median of warm calls; fps_256: the "
        "fast path (rasterise_hard + antialiased silhouette), fps_256_soft: the soft "
        f"rasteriser (tiles of 8, 128 faces per tile); shared 2-core CPU, load average {load:.1f}"
        " (timings inflated by the other jobs); benchmarks/bench_render.py has the full table"
    )
    return out, (vertices, faces)


def chunk_overflow(data, faces, opts2d) -> int:
    """Largest ``Fragments.overflow`` over the training heads' neutrals and their most
    displaced pose, every view (0: the fast path's chunk budget drops nothing)."""
    cameras = opts2d.cameras()
    worst = 0
    for h in range(data.n_heads):
        amplitude = np.abs(np.asarray(data.displacements[h])).reshape(
            data.displacements.shape[1], -1
        )
        pose = int(np.argmax(amplitude.max(1)))
        for v in (data.vertices[h], data.vertices[h] + data.displacements[h][pose]):
            for k in range(len(opts2d.yaw_degrees)):
                camera = jax.tree.map(lambda x, k=k: x[k], cameras)
                fragments = rasterise_hard(v, faces[h], camera, chunk_budget=opts2d.chunk_budget)
                worst = max(worst, int(fragments.overflow))
    return worst


FAST_GRADIENT_CHECK = """
import jax, sys
jax.config.update("jax_enable_x64", True)
import numpy as np, jax.numpy as jnp
from canrig_jax.render import interpolate, look_at, rasterise_hard, silhouette
data = np.load(sys.argv[1])
v0, faces = jnp.asarray(data["v"], jnp.float64), jnp.asarray(data["f"])
centre = np.asarray(v0.mean(0))
camera = look_at(centre + [0, 0, 60.0], centre, image_size=64)
rng = np.random.default_rng(0)
w = jnp.asarray(rng.standard_normal((2, 64, 64)))
attribute = jnp.asarray(rng.standard_normal((v0.shape[0], 1)))
for term in range(2):
    def loss(v):
        fragments = rasterise_hard(v, faces, camera)
        if term == 0:
            return jnp.sum(w[0] * silhouette(v, faces, camera, fragments))
        values = interpolate(v, faces, camera, fragments, attribute)
        return jnp.sum(w[1] * values.attributes[..., 0]) + 0.1 * jnp.sum(w[1] * values.depth)
    loss = jax.jit(loss)
    g = jax.grad(loss)(v0)
    u = jnp.asarray(rng.standard_normal(v0.shape)) * (jnp.abs(g) > 0)
    u = u / jnp.linalg.norm(u)
    fd = (loss(v0 + 1e-6 * u) - loss(v0 - 1e-6 * u)) / 2e-6
    print(float(jnp.abs(fd - jnp.sum(g * u)) / jnp.abs(fd)))
"""


def fast_path_checks(vertices, faces, centre, size, quick) -> dict:
    """The fast path (``rasterise_hard`` + ``interpolate`` + ``silhouette``): gradients vs
    finite differences (float64, a subprocess), visibility vs ray casting, speed at 256^2."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "head.npz"
        np.savez(path, v=np.asarray(vertices), f=np.asarray(faces))
        run = subprocess.run(
            [sys.executable, "-c", FAST_GRADIENT_CHECK, str(path)],
            capture_output=True,
            text=True,
            check=True,
        )
    errors = [float(x) for x in run.stdout.split()[-2:]]
    out["grad_rel_error_silhouette"], out["grad_rel_error_interpolation"] = errors
    out["grad_check"] = (
        "64^2, float64, visibility recomputed at each evaluation; a random direction over the "
        "vertices with a nonzero gradient, central difference 1e-6 cm; silhouette: antialiased "
        "mask; interpolation: a random attribute + 0.1 x depth"
    )
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=size)
    fragments = rasterise_hard(vertices, faces, camera)
    hit, depth = ray_cast(np.asarray(vertices), np.asarray(faces), camera)
    mask = np.asarray(fragments.covered)
    both = mask & hit
    error = np.abs(np.asarray(fragments.depth)[both] - depth[both]) * 10.0  # mm
    out["hard_vs_reference_iou"] = float(both.sum() / (mask | hit).sum())
    out["hard_vs_reference_depth_mm"] = {
        "median": float(np.median(error)),
        "q99": float(np.percentile(error, 99)),
        "fraction_within_0.1mm": float(np.mean(error < 0.1)),
    }
    out["overflow"] = int(fragments.overflow)
    return out


def build_data(args):
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=args.train_identities,
        n_test=args.test_identities,
        seed=args.seed,
        progress=not args.no_progress,
    )
    heads = dataset.train
    identities = sorted({h.name.split("/")[0] for h in heads})
    rigged_ids = set(identities[: args.rigged_identities])
    rigged = [i for i, h in enumerate(heads) if h.name.split("/")[0] in rigged_ids]
    return dataset, heads, rigged


def options_for(args, steps: int) -> RigAnyFaceTrainOptions:
    return RigAnyFaceTrainOptions(
        steps=steps,
        warmup_steps=max(1, min(50, steps // 5)),
        max_minutes=args.minutes,
        checkpoint_every=50,
        log_every=10,
        heads_per_step=2,
        poses_per_step=8,
        learning_rate=1e-3,
        seed=args.seed,
    )


def train_run(name, args, data, faces, poses, rigged, opts2d):
    stage1 = int(round(args.steps * args.stage1_fraction))
    progress = not args.no_progress
    if name == "3d_only":
        model, step, seconds, history = train_2d(
            data,
            faces,
            poses,
            rigged,
            options_for(args, args.steps),
            opts2d,
            stage="3d",
            checkpoint=args.out / "checkpoint_3d_only.eqx",
            progress=progress,
        )
        return model, {"steps": step, "seconds": seconds, "history": history}
    m1, s1, t1, h1 = train_2d(
        data,
        faces,
        poses,
        rigged,
        options_for(args, stage1),
        opts2d,
        stage="2d",
        checkpoint=args.out / "checkpoint_2d_stage1.eqx",
        progress=progress,
    )
    model, s2, t2, h2 = train_2d(
        data,
        faces,
        poses,
        rigged,
        options_for(args, args.steps - stage1),
        opts2d,
        stage="3d+2d",
        init=m1,
        checkpoint=args.out / "checkpoint_2d_stage2.eqx",
        progress=progress,
    )
    return model, {
        "steps": s1 + s2,
        "stage1_steps": s1,
        "stage2_steps": s2,
        "seconds": t1 + t2,
        "history": h1 + [{**r, "step": r["step"] + s1} for r in h2],
    }


def evaluate(models: dict, dataset, data_dir) -> dict:
    """Held-out ICT heads (all poses) and MakeHuman hm08 (its shared ARKit targets); the
    ``no_motion`` entry is the reference every method must beat."""
    poses = dataset.poses
    names = ["no_motion", *models]
    results = {name: {} for name in names}
    truth = [head.displacements for head in dataset.test["unseen_topology"]]
    for name in names:
        predicted = []
        for head in dataset.test["unseen_topology"]:
            if name == "no_motion":
                predicted.append(np.zeros_like(head.displacements))
                continue
            _, operators, _, _ = head_inputs(head.vertices, head.faces, k=128)
            out = generate_rig(models[name], poses, head.vertices, head.faces, operators=operators)
            predicted.append(out.displacements)
        stats = error_stats(np.concatenate(predicted, 1), np.concatenate(truth, 1))
        results[name]["ict_unseen_mae_mm"] = stats["mae_mm"]
        results[name]["ict_unseen_q95_mm"] = stats["q95_mm"]
        singles = error_stats(
            np.concatenate([p[: poses.n_basis] for p in predicted], 1),
            np.concatenate([t[: poses.n_basis] for t in truth], 1),
        )
        results[name]["ict_unseen_single_expressions_mae_mm"] = singles["mae_mm"]
        length = [np.linalg.norm(p, axis=-1).mean() for p in predicted]
        reference = [np.linalg.norm(t, axis=-1).mean() for t in truth]
        results[name]["ict_unseen_amplitude_ratio"] = float(np.sum(length) / np.sum(reference))
    mh = load_makehuman(data_dir)
    target_index, matrix = shared_shape_matrix(poses.basis_names, mh.names)
    target = mh.deltas[target_index]
    for name in names:
        if name == "no_motion":
            singles = np.zeros_like(target)
        else:
            p = generate_rig(models[name], poses, mh.neutral, mh.faces).displacements
            singles = np.einsum("sk,kvd->svd", matrix, p[: poses.n_basis])
        errors = sculpted_target_errors(singles, target, mh.skin)
        results[name]["makehuman_mae_mm"] = errors["skin_mae_mm"]
        results[name]["makehuman_active_mae_mm"] = errors["active_mae_mm"]
        results[name]["makehuman_amplitude_ratio_median"] = errors["amplitude_ratio_median"]
    return results


def figures(models: dict, dataset, out: Path):
    """Renders of the 2D model's generated rig's poses, and the 2D displacement field of one
    pose by every model and the ground truth."""
    head = dataset.test["unseen_topology"][0]
    poses = dataset.poses
    rig = generate_rig(models["2d_unrigged_plus_3d"], poses, head.vertices, head.faces)
    names = ["jawOpen", "mouthSmile_L", "eyeBlink_L", "browInnerUp_L"]
    ids = [poses.labels.index(n) for n in names if n in poses.labels]
    centre = head.vertices.mean(0)
    camera = look_at(centre + [0, 0, 55.0], centre + [0, 3.0, 0], image_size=256)
    fig, axes = plt.subplots(2, len(ids) + 1, figsize=(3 * (len(ids) + 1), 6))
    neutral, _ = lambert_image(head.vertices, head.faces, camera)
    axes[0, 0].imshow(neutral, cmap="gray", vmin=0, vmax=1)
    axes[0, 0].set_title("neutral")
    axes[1, 0].imshow(neutral, cmap="gray", vmin=0, vmax=1)
    axes[1, 0].set_title("neutral")
    for j, p in enumerate(ids, start=1):
        img, _ = lambert_image(head.vertices + rig.displacements[p], head.faces, camera)
        axes[0, j].imshow(img, cmap="gray", vmin=0, vmax=1)
        axes[0, j].set_title(f"generated: {poses.labels[p]}", fontsize=8)
        img, _ = lambert_image(head.vertices + head.displacements[p], head.faces, camera)
        axes[1, j].imshow(img, cmap="gray", vmin=0, vmax=1)
        axes[1, j].set_title(f"ground truth: {poses.labels[p]}", fontsize=8)
    for ax in axes.ravel():
        ax.axis("off")
    save_figure(fig, out / "rig_poses.png")
    plt.close(fig)
    p = poses.labels.index("jawOpen")
    panels = [
        (name, generate_rig(m, poses, head.vertices, head.faces).displacements[p])
        for name, m in models.items()
    ]
    panels.append(("ground truth", head.displacements[p]))
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 5))
    fields = [
        displacement_field(head.vertices, head.vertices + disp, head.faces, camera)
        for _, disp in panels
    ]
    flows = [np.asarray(f.attributes) * (np.asarray(f.silhouette) > 0.5)[..., None] for f in fields]
    top = max(float(np.percentile(np.linalg.norm(f, axis=-1), 99.5)) for f in flows)
    for ax, (title, _), flow in zip(axes, panels, flows, strict=True):
        im = ax.imshow(np.linalg.norm(flow, axis=-1), cmap="magma", vmin=0, vmax=top)
        step = 12
        rows, cols = np.mgrid[step // 2 : 256 : step, step // 2 : 256 : step]
        ax.quiver(
            cols,
            rows,
            flow[rows, cols, 0],
            flow[rows, cols, 1],
            color="cyan",
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.003,
        )
        ax.set_title(title, fontsize=10)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046, label="px")
    fig.suptitle("2D displacement of jawOpen on a held-out head (256^2, pixels)")
    save_figure(fig, out / "displacement_field.png")
    plt.close(fig)


def plot_history(histories: dict, path: Path):
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, h in histories.items():
        rows = [r for r in h if "error_mm" in r]
        if rows:
            ax.plot(
                [r["step"] for r in rows],
                [r["error_mm"] for r in rows],
                label=f"{name}: 3D error (rigged batch)",
            )
        rows = [r for r in h if "flow" in r]
        if rows:
            ax.plot(
                [r["step"] for r in rows],
                [r["flow"] for r in rows],
                "--",
                label=f"{name}: 2D displacement term",
            )
    ax.set_xlabel("step")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    save_figure(fig, path)
    plt.close(fig)


def table(r: dict) -> str:
    lines = ["# Issue 25: 2D supervision for RigAnyFace", "", "## Rasteriser", ""]
    ras = r["rasteriser"]
    lines += [
        "| quantity | value |",
        "|---|---|",
        f"| soft rasteriser: gradient vs finite differences (relative) | "
        f"{ras['grad_rel_error']:.2e} |",
        f"| soft rasteriser, hard limit vs ray casting: mask IoU | "
        f"{ras['hard_vs_reference_iou']:.4f} |",
        f"| soft rasteriser, hard limit vs ray casting: depth median / q99 (mm) | "
        f"{ras['hard_vs_reference_depth_mm']['median']:.2e} / "
        f"{ras['hard_vs_reference_depth_mm']['q99']:.3f} |",
        f"| forward + backward at 256^2 (frames/s), fast path | {ras['fps_256']:.2f} |",
    ]
    if "fps_256_soft" in ras:
        lines.append(
            f"| forward + backward at 256^2 (frames/s), soft rasteriser | "
            f"{ras['fps_256_soft']:.2f} |"
        )
    if "fast_path" in ras:
        fast = ras["fast_path"]
        lines += [
            f"| fast path: silhouette gradient vs finite differences (relative, float64) | "
            f"{fast['grad_rel_error_silhouette']:.2e} |",
            f"| fast path: interpolation gradient vs finite differences (relative, float64) | "
            f"{fast['grad_rel_error_interpolation']:.2e} |",
            f"| fast path: visibility vs ray casting: mask IoU | "
            f"{fast['hard_vs_reference_iou']:.4f} |",
            f"| fast path: visibility vs ray casting: depth median / q99 (mm) | "
            f"{fast['hard_vs_reference_depth_mm']['median']:.2e} / "
            f"{fast['hard_vs_reference_depth_mm']['q99']:.3f} |",
        ]
    lines += [
        "",
    ]
    if "training" in r:
        t = r["training"]
        lines += [
            "## Training (" + r["training_setup"]["summary"] + ")",
            "",
            "| method | ICT unseen MAE (mm) | q95 | single expressions MAE | amplitude ratio "
            "| MakeHuman skin MAE (mm) | active MAE | amplitude ratio (median) | steps | minutes |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name in ("no_motion", *RUNS):
            if name in t:
                e = t[name]
                steps = e.get("steps", "-")
                minutes = f"{e['seconds'] / 60:.1f}" if "seconds" in e else "-"
                lines.append(
                    f"| {name} | {e['ict_unseen_mae_mm']:.3f} | {e['ict_unseen_q95_mm']:.3f} | "
                    f"{e['ict_unseen_single_expressions_mae_mm']:.3f} | "
                    f"{e['ict_unseen_amplitude_ratio']:.2f} | "
                    f"{e['makehuman_mae_mm']:.3f} | {e['makehuman_active_mae_mm']:.3f} | "
                    f"{e['makehuman_amplitude_ratio_median']:.2f} | {steps} | {minutes} |"
                )
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--quick", action="store_true", help="tiny run for tests")
    parser.add_argument("--train-identities", type=int, default=8)
    parser.add_argument("--rigged-identities", type=int, default=2)
    parser.add_argument("--test-identities", type=int, default=4)
    parser.add_argument("--steps", type=int, default=400, help="steps of each method")
    parser.add_argument("--stage1-fraction", type=float, default=0.5)
    parser.add_argument("--minutes", type=float, default=None, help="clock budget per stage")
    parser.add_argument("--image-size", type=int, default=256)
    parser.add_argument("--poses-2d", type=int, default=2, help="rendered poses per head/step")
    parser.add_argument(
        "--rasteriser",
        choices=("fast", "soft"),
        default="fast",
        help="2D losses: hard visibility + interpolation + antialiasing (fast), or soft",
    )
    parser.add_argument("--views", type=float, nargs="+", default=[0.0, 35.0], help="yaws")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-only", choices=RUNS, default=None)
    parser.add_argument(
        "--rasteriser-only",
        action="store_true",
        help="only the rasteriser checks and speed, into --out/results.json (kept by later runs)",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.train_identities, args.rigged_identities, args.test_identities = 2, 1, 1
        args.steps, args.image_size = 4, 24
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    opts2d = Supervision2DOptions(
        image_size=args.image_size,
        poses_2d=args.poses_2d,
        yaw_degrees=tuple(args.views),
        rasteriser=args.rasteriser,
    )
    results = {"provenance": provenance(command)}
    previous = args.out / "results.json"
    if args.rasteriser_only or (args.train_only is None and not previous.exists()):
        results["rasteriser"], _ = rasteriser_checks(args.data_dir, args.quick)
        results["rasteriser"]["provenance"] = provenance(command)
        print("rasteriser:", {k: v for k, v in results["rasteriser"].items() if "note" not in k})
        if args.rasteriser_only:
            save_json(previous, results)
            save_text(args.out / "table.md", table(results))
            return
    elif args.train_only is None:  # the rasteriser section of an earlier --rasteriser-only run
        results["rasteriser"] = json.loads(previous.read_text())["rasteriser"]
    dataset, heads, rigged = build_data(args)
    data = training_set(heads, dataset.poses, k=128, progress=not args.no_progress)
    faces = padded_faces(heads)
    if opts2d.rasteriser == "fast" and args.train_only != "3d_only":
        overflow = chunk_overflow(data, faces, opts2d)
        print(f"fast rasteriser: chunks over budget on the training heads: {overflow}")
        if overflow:
            raise SystemExit("raise Supervision2DOptions.chunk_budget: some triangles are dropped")
    runs = RUNS if args.train_only is None else (args.train_only,)
    models, info = {}, {}
    for name in runs:
        models[name], info[name] = train_run(name, args, data, faces, dataset.poses, rigged, opts2d)
        print(f"trained {name}: {info[name]['steps']} steps, {info[name]['seconds'] / 60:.1f} min")
    if args.train_only is not None:
        return
    training = evaluate(models, dataset, args.data_dir)
    for name in runs:
        training[name].update({k: v for k, v in info[name].items() if k != "history"})
    results["training"] = training
    results["training_setup"] = {
        "summary": (
            f"{len(rigged)} rigged heads ({args.rigged_identities} identities x 2 resolutions), "
            f"{len(heads) - len(rigged)} unrigged heads (2D only), "
            f"{args.test_identities} held-out identities at decimate_1300; {args.steps} steps "
            f"per method, 2 heads x 8 poses per step"
        ),
        "rigged_heads": [heads[i].name for i in rigged],
        "unrigged_heads": [h.name for i, h in enumerate(heads) if i not in set(rigged)],
        "options_2d": opts2d.to_dict(),
        "stage1_fraction": args.stage1_fraction,
    }
    figures(models, dataset, args.out)
    plot_history({n: info[n]["history"] for n in runs}, args.out / "training_loss.png")
    save_json(args.out / "results.json", results)
    save_text(args.out / "table.md", table(results))
    record_command(args.out, command)
    print(table(results))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
