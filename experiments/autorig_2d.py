"""2D supervision for RigAnyFace: does training on renderings of heads that have no 3D rig
help? Trains (or resumes) both runs, evaluates them, and draws a generated rig.

    python experiments/autorig_2d.py --out experiments/results/autorig_2d            # standard
    python experiments/autorig_2d.py --out /tmp/autorig_2d --quick                   # tests

Training: ICT identities, remeshed as in ``experiments/autorig.py``; the first
``--rigged-identities`` keep their 3D rig, the others are "unrigged": only renderings of their
ground-truth poses (masks, 2D displacement, 2D landmarks from ``--views`` orthographic views)
reach the training. ``3d_only``: 3D loss on the rigged heads, ``--steps`` steps.
``2d_unrigged_plus_3d``: stage 1, 2D loss on all heads (``--stage1-fraction`` of the steps),
then stage 2, 3D + 2D on the rigged heads (the rest). Evaluation: held-out identities at a
resolution never trained on (``decimate_1300``; all 96 poses, MAE in mm) and the MakeHuman
hm08 head against its person-made targets (evaluation only: nothing is trained or tuned on it).
``experiments/autorig_2d_train.py RUN`` trains one run alone (same flags);
``experiments/autorig_2d_rasteriser.py`` measures the rasteriser (its checks and speed), which
this script measures too when DIR/results.json has no rasteriser section yet.

Writes DIR/results.json, DIR/table.md, DIR/rig_poses.png, DIR/displacement_field.png,
DIR/training_loss.png and the checkpoints (a rerun resumes them).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax._io import save_json, save_text
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.autorig import RigAnyFaceNetwork, ict_autorig_dataset, training_set
from canrig_jax.papers.riganyface import (
    SUPERVISION_2D_RUNS,
    chunk_overflow,
    evaluate_2d,
    padded_faces,
    parse_supervision_2d_args,
    rasteriser_checks,
    rigged_heads,
    supervision_2d_options,
    supervision_2d_table,
    train_2d_run,
)
from canrig_jax.render import displacement_field, lambert_image, look_at, save_figure
from canrig_jax.watchdog import run_watched


def figures(models: dict, dataset, out: Path):
    """Renders of the 2D model's generated rig's poses, and the 2D displacement field of one
    pose by every model and the ground truth."""
    head = dataset.test["unseen_topology"][0]
    poses = dataset.poses
    rig = RigAnyFaceNetwork((models["2d_unrigged_plus_3d"], poses)).generate(
        head.vertices, head.faces
    )
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
        (name, RigAnyFaceNetwork((m, poses)).generate(head.vertices, head.faces).displacements[p])
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    args = parse_supervision_2d_args(parser, argv)
    args.out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    opts2d = supervision_2d_options(args)
    results = {"provenance": provenance(command)}
    previous = args.out / "results.json"
    if previous.exists():  # the rasteriser section of an earlier run
        results["rasteriser"] = json.loads(previous.read_text())["rasteriser"]
    else:
        results["rasteriser"] = rasteriser_checks(args.data_dir, args.quick)
        results["rasteriser"]["provenance"] = provenance(command)
    dataset = ict_autorig_dataset(
        args.data_dir,
        n_train=args.train_identities,
        n_test=args.test_identities,
        seed=args.seed,
        progress=not args.no_progress,
    )
    heads, rigged = dataset.train, rigged_heads(dataset, args.rigged_identities)
    data = training_set(heads, dataset.poses, k=128, progress=not args.no_progress)
    faces = padded_faces(heads)
    if opts2d.rasteriser == "fast":
        overflow = chunk_overflow(data, faces, opts2d)
        print(f"fast rasteriser: chunks over budget on the training heads: {overflow}")
        if overflow:
            raise SystemExit("raise Supervision2DOptions.chunk_budget: some triangles are dropped")
    models, info = {}, {}
    for name in SUPERVISION_2D_RUNS:
        models[name], info[name] = train_2d_run(
            name, data, faces, dataset.poses, rigged, opts2d, folder=args.out, steps=args.steps,
            stage1_fraction=args.stage1_fraction, minutes=args.minutes, seed=args.seed,
            progress=not args.no_progress,
        )  # fmt: skip
        print(f"trained {name}: {info[name]['steps']} steps, {info[name]['seconds'] / 60:.1f} min")
    training = evaluate_2d(models, dataset, args.data_dir)
    for name in SUPERVISION_2D_RUNS:
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
    plot_history(
        {n: info[n]["history"] for n in SUPERVISION_2D_RUNS}, args.out / "training_loss.png"
    )
    save_json(args.out / "results.json", results)
    save_text(args.out / "table.md", supervision_2d_table(results))
    record_command(args.out, command)
    print(supervision_2d_table(results))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
