"""The RigAnyFace experiments' report: ``table.md`` of a results.json (the standard run's, or
an evaluation of checkpoints trained apart) and the figures (training loss, predicted poses
with their error maps, per-shape motion ratios).

Errors in the tables are millimetres; error maps run 0-5 mm.
"""

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from jaxtyping import ArrayLike, Float

from ..._metrics import CM_TO_MM
from ...autorig._data import RiggedHead
from ...autorig._makehuman import MakeHumanHead
from ...render import plot_vertex_scalar, save_figure
from ._heldout import UPPER_FACE
from ._makehuman import makehuman_shapes


def autorig_table(results: Mapping) -> str:
    """The markdown ``table.md`` of an auto-rigging results.json: with a ``"test"`` key (the
    standard run) the held-out tables, Table 1 (both splits, mm and unit sphere), Table 2
    (penetration), placement when measured and Table 3 (rig generation, sizes, training, glTF);
    without one (checkpoints evaluated apart) the held-out tables, penetration where the
    ground truth has none, and training."""
    if "test" not in results:
        text = [
            *_heldout_rows(results),
            "## Penetration (Table 2 analog)",
            *_penetration_clean_rows(results),
            "",
            *("## Training", "", "| quantity | value |", "|---|---|"),
            *_training_rows(results),
        ]
        return "\n".join(text) + "\n"
    rows = _heldout_rows(results) if "heldout" in results else []
    rows += _test_rows(results)
    rows += [
        "",
        "## Table 2 analog: penetration",
        "",
        "Fraction of teeth, gums and eyeball vertices outside the skin (winding number < 1/2),",
        "mean over poses and held-out heads.",
        "",
        "| | fraction |",
        "|---|---|",
    ]
    rows += [f"| {name} | {value:.4f} |" for name, value in results["penetration"].items()]
    rows += _penetration_clean_rows(results)
    rows += _placement_rows(results)
    rows += _timing_rows(results)
    rows += _training_rows(results)
    g = results["gltf"]
    rows += [
        f"| glTF export: morph targets / max abs difference after reload (cm) | "
        f"{g['morph_targets']} / {g['max_abs_difference_cm']:.2e} |"
    ]
    return "\n".join(rows) + "\n"


def _test_rows(r: Mapping) -> list[str]:
    rows = [
        "## Table 1 analog: held-out identities, vertex error in mm",
        "",
        "ICT cm -> mm; in brackets the same on heads normalised to the unit sphere, x 1000.",
        "",
        "| method | same topology MAE | same Q95 | unseen topology MAE | unseen Q95 |",
        "|---|---|---|---|---|",
    ]
    for name, splits in r["test"].items():
        s, u = splits["same_topology"], splits["unseen_topology"]
        rows.append(
            f"| {name} | {s['mae_mm']:.3f} ({s['mae_unit_sphere_x1000']:.3f}) | "
            f"{s['q95_mm']:.3f} ({s['q95_unit_sphere_x1000']:.3f}) | "
            f"{u['mae_mm']:.3f} ({u['mae_unit_sphere_x1000']:.3f}) | "
            f"{u['q95_mm']:.3f} ({u['q95_unit_sphere_x1000']:.3f}) |"
        )
    return rows


def _placement_rows(r: Mapping) -> list[str]:
    if "placement" not in r:
        return []
    p, e = r["placement_protocol"], r["placement"]
    sc = p["scale_cm"]
    rows = [
        "",
        f"## Placement: bounding box (as trained) or face ({p['model']}, {p['heads']} heads, "
        f"{p['split']})",
        "",
        f"Cut: {p['cut']}; compared on {p['compared_on']}. Face: {p['face']}. Mean scale "
        f"(cm): whole head box {sc['whole']['bounding_box_cm']:.2f} / face "
        f"{sc['whole']['face_cm']:.2f}; cut head box {sc['cut']['bounding_box_cm']:.2f} / "
        f"face {sc['cut']['face_cm']:.2f}. Face fit {p['seconds_face_fit_median']:.1f} s "
        "per head (median).",
        "",
        "| head | placement | MAE (mm) | q95 (mm) |",
        "|---|---|---|---|",
    ]
    return rows + [
        f"| {key.split('/')[0]} | {key.split('/')[1]} | {v['mae_mm']:.3f} | {v['q95_mm']:.3f} |"
        for key, v in e.items()
    ]


def _timing_rows(r: Mapping) -> list[str]:
    t = r["rig_seconds"]
    head = f"{t['vertices']} vertices, {t['poses']} poses"
    rows = [
        "",
        "## Table 3 analog: rig generation and size",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| rig generation ({head}), cold: compile + operators + network (s) | {t['cold']:.2f} |",
        f"| warm, a new head of similar size: operators + network (s) | {t['warm']:.2f} "
        f"({t['warm_operators']:.2f} + {t['warm_network']:.2f}) |",
    ]
    if "warm_orientation" in t:
        rows.append(f"| of which the orientation check (s) | {t['warm_orientation']:.3f} |")
    return rows


def _penetration_clean_rows(r: Mapping) -> list[str]:
    """Table of ``penetration_clean`` (none when results.json has no such key)."""
    if "penetration_clean" not in r:
        return []
    p = r["penetration_clean_protocol"]
    return [
        "",
        f"Where the ground truth has none ({p['heads']} heads, {p['split']}; "
        f"{p['selection']}; {min(p['poses_per_head'])}-{max(p['poses_per_head'])} poses "
        "per head): outside fraction of those (pose, vertex) pairs, and the fraction of "
        "those poses with any vertex outside. Plain penetration re-measured alongside.",
        "",
        "| method | outside fraction | poses with any | plain (re-measured) |",
        "|---|---|---|---|",
        *(
            f"| {name} | {c['fraction']:.5f} | {c['poses_with_any']:.3f} | "
            f"{r['penetration_remeasured'][name]:.4f} |"
            for name, c in r["penetration_clean"].items()
        ),
    ]


def _training_rows(r: Mapping) -> list[str]:
    """Table rows: parameters, steps, minutes and final training-batch error of each model."""
    return [f"| parameters {name} | {n:,} |" for name, n in r["parameters"].items()] + [
        f"| training {name}: steps / minutes / final batch error (mm) | {t['steps']} / "
        f"{t['minutes']:.1f} / {t['final_train_error_mm']:.3f} |"
        for name, t in r["training"].items()
    ]


def _heldout_rows(r: Mapping) -> list[str]:
    p = r["heldout_protocol"]
    rows = [
        f"## Held-out ICT identities ({p['heads']} heads, {p['split']}): vertex error in mm",
        "",
        f"Static: a (pose, vertex) pair whose ground-truth displacement is < {p['static_mm']} "
        "mm; moving: the others.",
        "",
        "| method | single MAE | single q95 | single static | single moving | "
        "combinations MAE | comb. q95 | comb. static | comb. moving |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, subsets in r["heldout"].items():
        cells = [
            f"{subsets[s][k]:.3f}"
            for s in ("single", "combinations")
            for k in ("mae_mm", "q95_mm", "static_mae_mm", "moving_mae_mm")
        ]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    rows += ["", "Worst five poses (MAE, mm):", "", "| method | worst poses |", "|---|---|"]
    for name, worst in r["worst_poses"].items():
        rows.append(
            f"| {name} | " + ", ".join(f"{w['pose']} {w['mae_mm']:.2f}" for w in worst) + " |"
        )
    if "heldout_shapes" in r:
        rows += ["", *_shape_region_rows(r["heldout_shapes"], "heldout_shapes.png")]
    return rows + _makehuman_rows(r)


def _makehuman_rows(r: Mapping) -> list[str]:
    m = r["makehuman_protocol"]
    rows = [
        "",
        f"## MakeHuman hm08 ({m['vertices']} vertices) against its person-made ARKit targets "
        f"({m['shared_shapes']} shapes shared with ICT), mm",
        "",
        f"Active: (shape, vertex) pairs the sculptor moved by more than {m['active_mm']} mm. "
        f"Alignment: {m['alignment']} (scale {m['fit_scale']:.3f}, trimmed RMS "
        f"{m['fit_trimmed_rms_cm'] * 10:.2f} mm). Evaluation only: nothing trained or tuned on "
        "it.",
        "",
        "| method | MAE skin | q95 skin | MAE active | amplitude ratio (median) |",
        "|---|---|---|---|---|",
    ]
    for name, e in r["makehuman"].items():
        rows.append(
            f"| {name} | {e['skin_mae_mm']:.3f} | {e['skin_q95_mm']:.2f} | "
            f"{e['active_mae_mm']:.2f} | {e['amplitude_ratio_median']:.2f} |"
        )
    matched = ", ".join(f"{k} -> {v}" for k, v in m["matched_parts"].items())
    rows += ["", f"Part matching (MakeHuman component -> ICT part): {matched}.", ""]
    if "makehuman_shapes" in r:
        rows += _shape_region_rows(r["makehuman_shapes"], "makehuman_shapes.png")
    return rows


def _shape_region_rows(shapes: Mapping, figure: str) -> list[str]:
    """Markdown rows: each method's median per-shape amplitude ratio, peak ratio and skin MAE
    (mm) on the upper face (``UPPER_FACE`` shapes) and on the rest, from a
    ``makehuman_shapes`` or ``heldout_shapes`` record; ``figure`` names its figure."""
    upper = np.asarray(shapes["upper_face"])
    rows = [
        f"Per shape, by region (median over shapes; upper face: {', '.join(UPPER_FACE)}*, "
        f"{upper.sum()} shapes; lower face: the other {(~upper).sum()}; {figure}):",
        "",
        "| method | amplitude ratio upper / lower | peak ratio upper / lower | "
        "skin MAE upper / lower (mm) |",
        "|---|---|---|---|",
    ]
    for name, e in shapes["methods"].items():
        ratio, mae = np.asarray(e["amplitude_ratio"]), np.asarray(e["skin_mae_mm"])
        peak = np.asarray(e["peak_ratio"])
        cells = [
            f"{np.median(x[upper]):{f}} / {np.median(x[~upper]):{f}}"
            for x, f in ((ratio, ".2f"), (peak, ".2f"), (mae, ".3f"))
        ]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return [*rows, "", "Amplitude: summed motion on the skin; peak: its largest vertex motion.", ""]


def plot_training_history(training: Mapping[str, Mapping], path: str | Path) -> None:
    """Each model's logged training-batch mean vertex error (mm, log scale) against the step
    (``training``: name -> a record with its ``"history"``), saved as a PNG at ``path``."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, t in training.items():
        steps = [h["step"] for h in t["history"]]
        ax.plot(steps, [h["error_mm"] for h in t["history"]], label=name, lw=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("training batch mean vertex error (mm)")
    ax.set_yscale("log")
    ax.legend()
    save_figure(fig, path)


def plot_pose_examples(
    out: str | Path,
    labels: Sequence[str],
    examples: Mapping[str, tuple[RiggedHead, Mapping[str, Float[ArrayLike, "P _V 3"]]]],
    makehuman_example: tuple[
        MakeHumanHead,
        Float[ArrayLike, "S Vm 3"],
        Mapping[str, Float[ArrayLike, "S Vm 3"]],
        Sequence[str],
    ],
) -> None:
    """``out``/poses_<split>.png of each held-out example (split -> (head, row -> (P, V, 3)
    predictions)) on its skin (parts 0 and 1), ``out``/makehuman.png and
    ``out``/makehuman_shapes.png (``evaluate_makehuman``'s example; ``makehuman_shapes``).
    ``labels``: the P pose labels."""
    out = Path(out)
    for split, (head, predictions) in examples.items():
        skin = head.parts <= 1
        _plot_poses(
            head.vertices,
            head.faces[skin[head.faces].all(axis=1)],
            head.displacements,
            predictions,
            labels,
            out / f"poses_{split}.png",
        )
    mh, truth, predictions, mh_labels = makehuman_example
    _plot_poses(
        mh.neutral,
        mh.faces[mh.skin[mh.faces].all(axis=1)],
        truth,
        predictions,
        mh_labels,
        out / "makehuman.png",
    )
    plot_shape_ratios(
        makehuman_shapes(makehuman_example),
        "MakeHuman hm08 against its sculpted targets",
        out / "makehuman_shapes.png",
    )


def _wrapped(name: str) -> str:
    """A method's name broken at its folder and placement so that figure columns do not overlap."""
    return name.replace("/", "/\n").replace(" + ", "\n+ ")


def plot_shape_ratios(shapes: Mapping, title: str, path: str | Path) -> None:
    """Each method's per-shape amplitude ratio (summed motion on the skin) and peak ratio
    (largest vertex motion), generated over true (log scale; 1: the true amount), shapes in
    alphabetical order, the upper face shaded (``makehuman_shapes``, ``heldout_shapes``)."""
    labels = shapes["labels"]
    order = np.argsort(labels)
    upper = np.asarray(shapes["upper_face"])[order]
    fig, axes = plt.subplots(2, 1, figsize=(13, 7.5), sharex=True)
    for ax, key, what in zip(
        axes, ("amplitude_ratio", "peak_ratio"), ("summed motion", "peak motion"), strict=True
    ):
        for x in np.flatnonzero(upper):
            ax.axvspan(x - 0.5, x + 0.5, color="0.92", lw=0)
        for name, e in shapes["methods"].items():
            ratio = np.maximum(np.asarray(e[key])[order], 1e-2)
            ax.plot(np.arange(len(labels)), ratio, "o-", ms=3, lw=0.7, label=name)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_yscale("log")
        ax.set_ylabel(f"{what} on the skin,\ngenerated / true")
    axes[1].set_xticks(np.arange(len(labels)), [labels[i] for i in order], rotation=90, fontsize=7)
    axes[1].set_xlim(-0.5, len(labels) - 0.5)
    axes[0].set_title(f"{title}, per shape (grey: upper face)")
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the data
    save_figure(fig, path)


def _plot_poses(vertices, faces, truth, predictions: Mapping, labels, path, n_poses: int = 4):
    """Ground truth and each method's prediction for the ``n_poses`` poses that move most,
    coloured by error (0-5 mm; the ground truth by its displacement), on ``faces`` (e.g. the
    skin). ``truth`` and each prediction: (P, V, 3) cm."""
    size = np.linalg.norm(truth, axis=-1).mean(axis=1)
    chosen = np.argsort(-size)[:n_poses]
    columns = ["ground_truth", *predictions]
    fig, axes = plt.subplots(n_poses, len(columns), figsize=(3 * len(columns), 3.2 * n_poses))
    for row, p in enumerate(chosen):
        for col, name in enumerate(columns):
            displaced = truth[p] if name == "ground_truth" else predictions[name][p]
            if name == "ground_truth":
                values = np.linalg.norm(truth[p], axis=-1) * CM_TO_MM
            else:
                values = np.linalg.norm(displaced - truth[p], axis=-1) * CM_TO_MM
            mappable = plot_vertex_scalar(
                axes[row, col],
                vertices + displaced,
                faces,
                values,
                vmax=5.0,
                title=f"{_wrapped(name)}\n{labels[p]}" if row == 0 or col == 0 else None,
            )
    fig.colorbar(
        mappable, ax=axes, shrink=0.5, label="mm (ground truth: displacement; others: error)"
    )
    save_figure(fig, path)
