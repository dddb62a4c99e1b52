"""The 2D-supervision experiment's protocols (``experiments/autorig_2d*.py``): the
rasteriser's checks (gradients against finite differences, the hard limit and the fast path
against ray casting, frames per second), the command line and recipe of its two training runs
(3D only on the rigged heads; 2D on every head, then 3D + 2D on the rigged ones), and their
evaluation on held-out ICT identities and the MakeHuman head.

Lengths in centimetres, errors in millimetres, images in pixels.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Int

from ...autorig._data import AutorigDataset, PoseSet
from ...autorig._evaluation import sculpted_target_errors, shared_shape_matrix
from ...autorig._makehuman import load_makehuman
from ...autorig._metrics import error_stats
from ...autorig._model import RigAnyFace
from ...autorig._rig import generate_rig
from ...autorig._supervision_2d import Supervision2DOptions, train_2d
from ...autorig._train import RigAnyFaceTrainOptions, TrainingSet, head_inputs
from ...data import load_ict
from ...mesh import decimate
from ...render import RasterSettings, look_at, rasterise, rasterise_hard, ray_cast, silhouette

SUPERVISION_2D_RUNS = ("3d_only", "2d_unrigged_plus_3d")
"""The two training runs: 3D loss on the rigged heads only; and 2D loss on every head (stage
1) then 3D + 2D on the rigged heads (stage 2)."""

_QUICK = {
    "train_identities": 2,
    "rigged_identities": 1,
    "test_identities": 1,
    "steps": 4,
    "image_size": 24,
}


def parse_supervision_2d_args(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None = None
) -> argparse.Namespace:
    """Add the 2D experiment's shared options to ``parser`` (data, identities, steps, stage
    split, clock budget, views, image size, rasteriser, seed, ``--quick``), parse ``argv`` and
    return the namespace; ``--quick`` makes it tiny (2 training identities, 1 rigged, 1
    held out, 4 steps, 24^2 images)."""
    add = parser.add_argument
    add("--data-dir", default=None, help="data folder (else $CANRIG_DATA)")
    add("--quick", action="store_true", help="tiny run for tests")
    add("--train-identities", type=int, default=8)
    add("--rigged-identities", type=int, default=2)
    add("--test-identities", type=int, default=4)
    add("--steps", type=int, default=400, help="steps of each method")
    add("--stage1-fraction", type=float, default=0.5)
    add("--minutes", type=float, default=None, help="clock budget per stage")
    add("--image-size", type=int, default=256)
    add("--poses-2d", type=int, default=2, help="rendered poses per head/step")
    add(
        "--rasteriser",
        choices=("fast", "soft"),
        default="fast",
        help="2D losses: hard visibility + interpolation + antialiasing (fast), or soft",
    )
    add("--views", type=float, nargs="+", default=[0.0, 35.0], help="yaws")
    add("--seed", type=int, default=0)
    add("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        vars(args).update(_QUICK)
    return args


def supervision_2d_options(args: argparse.Namespace) -> Supervision2DOptions:
    """The 2D loss's options of a namespace from ``parse_supervision_2d_args``."""
    return Supervision2DOptions(
        image_size=args.image_size,
        poses_2d=args.poses_2d,
        yaw_degrees=tuple(args.views),
        rasteriser=args.rasteriser,
    )


def rigged_heads(dataset: AutorigDataset, rigged_identities: int) -> list[int]:
    """Indices into ``dataset.train`` of the heads that keep their 3D rig: those of the first
    ``rigged_identities`` identities in sorted order (every resolution of each); the others
    reach training only through renderings."""
    identities = sorted({h.name.split("/")[0] for h in dataset.train})
    kept = set(identities[:rigged_identities])
    return [i for i, h in enumerate(dataset.train) if h.name.split("/")[0] in kept]


def _options(steps: int, minutes: float | None, seed: int) -> RigAnyFaceTrainOptions:
    """One stage's options: 2 heads x 8 poses per step, warm-up a fifth (at most 50)."""
    return RigAnyFaceTrainOptions(
        steps=steps,
        warmup_steps=max(1, min(50, steps // 5)),
        max_minutes=minutes,
        checkpoint_every=50,
        log_every=10,
        heads_per_step=2,
        poses_per_step=8,
        learning_rate=1e-3,
        seed=seed,
    )


def train_2d_run(
    name: str,
    data: TrainingSet,
    faces: Int[ArrayLike, "N F 3"],
    poses: PoseSet,
    rigged: Sequence[int],
    opts2d: Supervision2DOptions,
    *,
    folder: str | Path,
    steps: int,
    stage1_fraction: float = 0.5,
    minutes: float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> tuple[RigAnyFace, dict]:
    """Train (or resume) one of ``SUPERVISION_2D_RUNS`` in ``folder``: ``"3d_only"``, ``steps``
    steps of 3D loss on the ``rigged`` heads (checkpoint_3d_only.eqx); or
    ``"2d_unrigged_plus_3d"``, ``round(steps * stage1_fraction)`` steps of 2D loss on every
    head (checkpoint_2d_stage1.eqx) then the rest with 3D + 2D on the rigged heads, starting
    from stage 1's model (checkpoint_2d_stage2.eqx). ``minutes``: clock budget per stage.

    Returns (model, {"steps", "seconds", "history"}, and for the two-stage run
    "stage1_steps", "stage2_steps"; the history's steps counted from the first stage's
    start})."""
    if name not in SUPERVISION_2D_RUNS:
        raise ValueError(f"name: expected one of {SUPERVISION_2D_RUNS}, got {name!r}")
    folder = Path(folder)
    if name == "3d_only":
        model, step, seconds, history = train_2d(
            data, faces, poses, rigged, _options(steps, minutes, seed), opts2d, stage="3d",
            checkpoint=folder / "checkpoint_3d_only.eqx", progress=progress,
        )  # fmt: skip
        return model, {"steps": step, "seconds": seconds, "history": history}
    stage1 = int(round(steps * stage1_fraction))
    m1, s1, t1, h1 = train_2d(
        data, faces, poses, rigged, _options(stage1, minutes, seed), opts2d, stage="2d",
        checkpoint=folder / "checkpoint_2d_stage1.eqx", progress=progress,
    )  # fmt: skip
    model, s2, t2, h2 = train_2d(
        data, faces, poses, rigged, _options(steps - stage1, minutes, seed), opts2d,
        stage="3d+2d", init=m1, checkpoint=folder / "checkpoint_2d_stage2.eqx",
        progress=progress,
    )  # fmt: skip
    return model, {
        "steps": s1 + s2,
        "stage1_steps": s1,
        "stage2_steps": s2,
        "seconds": t1 + t2,
        "history": h1 + [{**r, "step": r["step"] + s1} for r in h2],
    }


def chunk_overflow(
    data: TrainingSet,
    faces: Int[np.ndarray, "N F 3"] | Int[Array, "N F 3"],
    opts2d: Supervision2DOptions,
) -> int:
    """Largest ``Fragments.overflow`` of the fast rasteriser over the training heads' neutrals
    and their most displaced pose, in every view of ``opts2d`` (0: its chunk budget drops no
    triangle)."""
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


def evaluate_2d(
    models: Mapping[str, RigAnyFace],
    dataset: AutorigDataset,
    data_dir: str | os.PathLike | None = None,
) -> dict[str, dict]:
    """Each model and no motion (the reference every method must beat) on the held-out ICT
    heads at the unseen resolution (all poses; single expressions; the predicted over the
    true mean displacement length) and on the MakeHuman hm08 head against its person-made
    ARKit targets (``sculpted_target_errors``): row -> {"ict_unseen_mae_mm",
    "ict_unseen_q95_mm", "ict_unseen_single_expressions_mae_mm", "ict_unseen_amplitude_ratio",
    "makehuman_mae_mm", "makehuman_active_mae_mm", "makehuman_amplitude_ratio_median"}."""
    poses = dataset.poses
    names = ["no_motion", *models]
    results: dict[str, dict] = {name: {} for name in names}
    heads = dataset.test["unseen_topology"]
    truth = [head.displacements for head in heads]
    for name in names:
        predicted = []
        for head in heads:
            if name == "no_motion":
                predicted.append(np.zeros_like(head.displacements))
                continue
            _, operators, _, _ = head_inputs(head.vertices, head.faces, k=128)
            out = generate_rig(models[name], poses, head.vertices, head.faces, operators=operators)
            predicted.append(out.displacements)
        results[name].update(_ict_errors(predicted, truth, poses.n_basis))
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


def _ict_errors(predicted: list, truth: list, n_basis: int) -> dict[str, float]:
    stats = error_stats(np.concatenate(predicted, 1), np.concatenate(truth, 1))
    singles = error_stats(
        np.concatenate([p[:n_basis] for p in predicted], 1),
        np.concatenate([t[:n_basis] for t in truth], 1),
    )
    length = [np.linalg.norm(p, axis=-1).mean() for p in predicted]
    reference = [np.linalg.norm(t, axis=-1).mean() for t in truth]
    return {
        "ict_unseen_mae_mm": stats["mae_mm"],
        "ict_unseen_q95_mm": stats["q95_mm"],
        "ict_unseen_single_expressions_mae_mm": singles["mae_mm"],
        "ict_unseen_amplitude_ratio": float(np.sum(length) / np.sum(reference)),
    }


def rasteriser_checks(data_dir: str | os.PathLike | None = None, quick: bool = False) -> dict:
    """The rasteriser on the generic ICT head (all parts) decimated to ~1,750 vertices: the
    soft rasteriser's gradient against a central difference (relative error), its hard limit
    and the fast path (``rasterise_hard``) against NumPy ray casting (mask IoU, depth error in
    mm), and forward + backward frames per second at 256^2 of both (``quick``: smaller images,
    fewer repeats)."""
    ict = load_ict(data_dir, parts=None)
    d = decimate(ict.neutral, ict.faces, 1750)
    vertices = jnp.asarray(d.vertices, jnp.float32)
    faces = jnp.asarray(d.faces, jnp.int32)
    centre = np.asarray(vertices.mean(0))
    out: dict = {
        "head": f"ICT generic head, all parts, decimated: {len(d.vertices)} v, {len(faces)} f"
    }
    out.update(_soft_gradient_check(vertices, faces, centre))
    size = 48 if quick else 128
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=size)
    hard = rasterise(
        vertices, faces, camera, settings=RasterSettings.hard(faces_per_tile=faces.shape[0])
    )
    out.update(_against_ray_casting(vertices, faces, camera, hard.silhouette > 0.5, hard.depth))
    out["hard_reference"] = f"NumPy Moeller-Trumbore ray casting, {size}^2, perspective 30 deg"
    out["fast_path"] = _fast_path_checks(vertices, faces, camera)
    out.update(_frames_per_second(vertices, faces, centre, 2 if quick else 5))
    return out


def _soft_gradient_check(vertices, faces, centre) -> dict:
    """Directional derivative along the gradient of a silhouette + depth loss (32^2, float32)
    against a central difference of 2e-3 cm."""
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
    return {
        "grad_rel_error": float(jnp.abs(fd - jnp.sum(grad * direction)) / jnp.abs(fd)),
        "grad_check": "silhouette + depth loss, 32^2, sigma 1 px, gamma 0.5; directional "
        "derivative along the gradient vs central difference (2e-3 cm), float32",
    }


def _against_ray_casting(vertices, faces, camera, covered, depth) -> dict:
    """Mask IoU and depth error (mm) of a rendering (``covered`` mask, ``depth``) against
    NumPy ray casting of the same camera."""
    hit, reference = ray_cast(np.asarray(vertices), np.asarray(faces), camera)
    mask = np.asarray(covered)
    both = mask & hit
    error = np.abs(np.asarray(depth)[both] - reference[both]) * 10.0  # mm
    return {
        "hard_vs_reference_iou": float(both.sum() / (mask | hit).sum()),
        "hard_vs_reference_depth_mm": {
            "median": float(np.median(error)),
            "q99": float(np.percentile(error, 99)),
            "fraction_within_0.1mm": float(np.mean(error < 0.1)),
        },
    }


_FAST_GRADIENT_CHECK = """
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
"""The fast path's gradient check, run in a child process (float64 needs ``jax_enable_x64``
from the start)."""


def _fast_path_checks(vertices, faces, camera) -> dict:
    """The fast path (``rasterise_hard`` + ``interpolate`` + ``silhouette``): gradients vs
    finite differences (float64, a child process) and visibility vs ray casting (``camera``)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "head.npz"
        np.savez(path, v=np.asarray(vertices), f=np.asarray(faces))
        run = subprocess.run(
            [sys.executable, "-c", _FAST_GRADIENT_CHECK, str(path)],
            capture_output=True,
            text=True,
            check=True,
        )
    silhouette_error, interpolation_error = (float(x) for x in run.stdout.split()[-2:])
    fragments = rasterise_hard(vertices, faces, camera)
    return {
        "grad_rel_error_silhouette": silhouette_error,
        "grad_rel_error_interpolation": interpolation_error,
        "grad_check": "64^2, float64, visibility recomputed at each evaluation; a random "
        "direction over the vertices with a nonzero gradient, central difference 1e-6 cm; "
        "silhouette: antialiased mask; interpolation: a random attribute + 0.1 x depth",
        **_against_ray_casting(vertices, faces, camera, fragments.covered, fragments.depth),
        "overflow": int(fragments.overflow),
    }


def _frames_per_second(vertices, faces, centre, repeats: int) -> dict:
    """Forward + backward of a silhouette loss at 256^2 per second (median of warm calls), by
    the fast path and by the soft rasteriser."""
    camera = look_at(centre + [0, 0, 60.0], centre, image_size=256)
    default = RasterSettings()
    shifted = vertices + jnp.asarray([0.3, 0.2, 0.0])
    renders = {
        "fps_256": lambda v: silhouette(v, faces, camera),
        "fps_256_soft": lambda v: rasterise(v, faces, camera, settings=default).silhouette,
    }
    out = {}
    for key, render in renders.items():
        target = render(shifted)

        @jax.jit
        def step(v, render=render, target=target):
            return jax.value_and_grad(lambda v: jnp.mean((render(v) - target) ** 2))(v)

        jax.block_until_ready(step(vertices))
        times = []
        for _ in range(repeats if key == "fps_256" else min(repeats, 3)):
            start = time.perf_counter()
            jax.block_until_ready(step(vertices + 0.01))
            times.append(time.perf_counter() - start)
        out[key] = float(1.0 / np.median(times))
    load = os.getloadavg()[0]
    out["fps_256_note"] = (
        "forward + backward of a silhouette loss, 256^2, median of warm calls; fps_256: the "
        "fast path (rasterise_hard + antialiased silhouette), fps_256_soft: the soft "
        f"rasteriser (tiles of 8, 128 faces per tile); shared 2-core CPU, load average {load:.1f}"
        " (timings inflated by the other jobs); benchmarks/bench_render.py has the full table"
    )
    return out


def supervision_2d_table(results: Mapping) -> str:
    """The markdown ``table.md`` of the 2D experiment's results.json: the rasteriser's checks
    and speed, and, once trained, each run's held-out and MakeHuman errors (mm) beside no
    motion."""
    ras = results["rasteriser"]
    lines = ["# Issue 25: 2D supervision for RigAnyFace", "", "## Rasteriser", ""]
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
    lines.append("")
    if "training" in results:
        lines += _training_table(results["training"], results["training_setup"]["summary"])
    return "\n".join(lines) + "\n"


def _training_table(t: Mapping, summary: str) -> list[str]:
    lines = [
        "## Training (" + summary + ")",
        "",
        "| method | ICT unseen MAE (mm) | q95 | single expressions MAE | amplitude ratio "
        "| MakeHuman skin MAE (mm) | active MAE | amplitude ratio (median) | steps | minutes |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("no_motion", *SUPERVISION_2D_RUNS):
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
    return lines
