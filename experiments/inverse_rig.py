"""Racković et al. 2023's protocol on the ict-quartic rig: alpha sweep, method comparison,
coordinate orders, speed against the published NumPy algorithm.

    python experiments/inverse_rig.py --out experiments/results/inverse_rig
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import jax
import matplotlib.pyplot as plt
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ reference

from benchmarks.inverse_reference import measure_reference  # noqa: E402
from canrig_jax import inverse  # noqa: E402
from canrig_jax.data import load_livelinkface  # noqa: E402
from canrig_jax.inverse.metrics import roughness, select_alpha, summarize  # noqa: E402
from canrig_jax.io import save_json, save_text  # noqa: E402
from canrig_jax.metrics import CM_TO_MM, per_vertex_distance  # noqa: E402
from canrig_jax.render import plot_vertex_scalar, save_figure  # noqa: E402
from canrig_jax.rig import evaluate, ict_quartic_rig  # noqa: E402
from canrig_jax.rig.poses import random_sparse_poses  # noqa: E402

NOISE_VARIANCE = 0.03  # cm^2, as in the paper
SWEEP = {
    "quartic_cd": lambda a: inverse.QuarticCD(alpha=a, passes=5),
    "linear_cd": lambda a: inverse.LinearCD(alpha=a, passes=5),
    "cetinaslan": lambda a: inverse.Cetinaslan(alpha=a),
    "lmmm": lambda a: inverse.LMMM(alpha=a, iterations=50),
}
FIXED = {
    "seol": lambda a: inverse.Seol(),
    "joshi": lambda a: inverse.Joshi(),
    "jaxopt_lbfgsb": lambda a: inverse.JaxoptLBFGSB(alpha=a),
}


@functools.partial(jax.jit, static_argnames="order")
def _solve_all(problem, targets, method, order):
    # the method is an argument, so an alpha sweep compiles once per method
    return jax.vmap(lambda b: inverse.solve(problem, b, method, order=order))(targets).weights


def take_scores(rig, weights, clean, alpha, seconds):
    """One table row: the method's alpha, frame metrics, roughness and speed on the take."""
    scores = {"alpha": alpha, **summarize(rig, weights, clean), "roughness": roughness(weights)}
    return {**scores, "seconds_per_frame": seconds}


def run(problem, targets, method, order="decreasing"):
    """Solve all frames in one jitted vmap; returns weights and seconds per frame."""
    _solve_all(problem, targets, method, order).block_until_ready()  # compile, warm up
    start = time.perf_counter()
    weights = np.asarray(_solve_all(problem, targets, method, order))
    return weights, (time.perf_counter() - start) / len(targets)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--quick", action="store_true", help="30 frames, 20 poses, 3 alphas")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    rig, _ = ict_quartic_rig(args.data_dir)
    problem = inverse.prepare(rig)
    meshes = jax.jit(jax.vmap(evaluate, (None, 0)))
    take = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    train = random_sparse_poses(rng, 20 if args.quick else 100, rig.names)
    if args.quick:
        take = take[:30]
    alphas = [0.0, 0.5, 5.0] if args.quick else [0.0, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
    noise = np.sqrt(NOISE_VARIANCE)
    clean_train, clean_test = np.asarray(meshes(rig, train)), np.asarray(meshes(rig, take))
    noisy_train = clean_train + rng.normal(0, noise, clean_train.shape).astype(np.float32)
    noisy_test = clean_test + rng.normal(0, noise, clean_test.shape).astype(np.float32)

    sweep = {}
    for name, make in SWEEP.items():
        sweep[name] = []
        for alpha in alphas:
            weights, _ = run(problem, noisy_train, make(alpha))
            sweep[name].append({"alpha": alpha, **summarize(rig, weights, clean_train)})
            print(f"sweep {name} alpha={alpha}: {sweep[name][-1]}", flush=True)
    chosen = {name: select_alpha(rows)["alpha"] for name, rows in sweep.items()}
    chosen.update(seol=0.0, joshi=0.0, jaxopt_lbfgsb=chosen["quartic_cd"])

    methods, take_weights = {}, {}
    for name, make in {**SWEEP, **FIXED}.items():
        weights, seconds = run(problem, noisy_test, make(chosen[name]))
        take_weights[name] = weights
        methods[name] = take_scores(rig, weights, clean_test, chosen[name], seconds)
        print(f"test {name}: {methods[name]}", flush=True)
    truth = {"alpha": None, **summarize(rig, take, clean_test), "roughness": roughness(take)}

    orderings = {}
    for order in inverse.ORDERS:
        weights, seconds = run(
            problem, noisy_test, SWEEP["quartic_cd"](chosen["quartic_cd"]), order
        )
        orderings[order] = take_scores(rig, weights, clean_test, chosen["quartic_cd"], seconds)
        print(f"order {order}: {orderings[order]}", flush=True)

    passes = {}  # convergence of Algorithm 1 with the number of passes, at the chosen alpha
    for n in (1, 2, 5) if args.quick else (1, 2, 5, 10, 20, 50):
        method = inverse.QuarticCD(alpha=chosen["quartic_cd"], passes=n)
        weights, seconds = run(problem, noisy_test, method)
        passes[str(n)] = take_scores(rig, weights, clean_test, chosen["quartic_cd"], seconds)
        print(f"passes {n}: {passes[str(n)]}", flush=True)

    reference = measure_reference(
        rig,
        noisy_test,
        alpha=chosen["quartic_cd"],
        passes=5,
        n_reference_frames=1 if args.quick else 3,
    )
    results = {
        "sweep": sweep,
        "methods": methods,
        "orderings": orderings,
        "passes": passes,
        "reference": reference,
        "ground_truth": truth,
        "protocol": {
            "test_frames": len(take),
            "train_poses": len(train),
            "noise_variance_cm2": NOISE_VARIANCE,
            "alpha_rule": "largest alpha with training mean RMSE within 5% of the method's best",
            "cardinality_tol": inverse.metrics.CARDINALITY_TOL,
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    save_text(args.out / "table.md", _table(methods, truth, orderings, passes, reference))
    _tradeoff_plot(sweep, chosen, args.out / "tradeoff.png")
    _weight_curves(rig, take, take_weights, args.out / "weight_curves.png")
    _error_maps(rig, take_weights, clean_test, args.out / "error_maps.png")
    print((args.out / "table.md").read_text())
    print(f"wrote {args.out}")
    return results


COLUMNS = (
    "alpha",
    "rmse_mean_mm",
    "rmse_p95_mm",
    "cardinality",
    "l1",
    "roughness",
    "seconds_per_frame",
)


def _row(name, values):
    cells = []
    for key in COLUMNS:
        value = values.get(key)
        cells.append("–" if value is None else f"{value:.4g}")
    return f"| {name} | " + " | ".join(cells) + " |\n"


def _table(methods, truth, orderings, passes, reference):
    head = "| method | " + " | ".join(COLUMNS) + " |\n" + "|---" * (len(COLUMNS) + 1) + "|\n"
    text = "## Methods on the noisy Live Link take (Table 3 layout)\n\n" + head
    text += _row("ground truth", truth)
    text += "".join(_row(name, values) for name, values in methods.items())
    text += "\n## Coordinate orders, QuarticCD (Table 8 analog)\n\n" + head
    text += "".join(_row(name, values) for name, values in orderings.items())
    text += "\n## QuarticCD against the number of passes (decreasing order)\n\n" + head
    text += "".join(_row(f"{n} passes", values) for n, values in passes.items())
    text += (
        "\n## Speed against Algorithm 1 as published (NumPy, full rig per coordinate)\n\n"
        "| numpy s/frame | jax s/frame | speedup | max weight difference |\n|---|---|---|---|\n"
        f"| {reference['numpy_seconds_per_frame']:.3g} | {reference['jax_seconds_per_frame']:.3g}"
        f" | {reference['speedup']:.0f}x | {reference['max_weight_difference']:.2g} |\n"
    )
    return text


def _tradeoff_plot(sweep, chosen, path):
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, label in zip(axes, ("rmse_mean_mm", "rmse_p95_mm"), ("mean", "p95"), strict=True):
        for name, rows in sweep.items():
            card = [r["cardinality"] for r in rows]
            err = [r[key] for r in rows]
            sizes = [20 + 25 * r["alpha"] for r in rows]
            ax.plot(card, err, "-", alpha=0.4)
            ax.scatter(card, err, s=sizes, label=name)
            pick = next(r for r in rows if r["alpha"] == chosen[name])
            ax.scatter([pick["cardinality"]], [pick[key]], s=120, facecolors="none", edgecolors="k")
        ax.set_xlabel("cardinality (weights > 1e-3)")
        ax.set_ylabel(f"{label} error (mm)")
        ax.set_title(f"{label} error vs cardinality", fontsize=10)
    axes[0].legend(title="dot size: alpha; ring: chosen", fontsize=8, title_fontsize=8)
    save_figure(fig, path)


def _weight_curves(rig, truth, take_weights, path, methods=("quartic_cd", "joshi", "cetinaslan")):
    shapes = np.argsort(-truth.max(axis=0))[:5]
    fig, axes = plt.subplots(1, len(methods), figsize=(5 * len(methods), 3.5), sharey=True)
    for ax, name in zip(axes, methods, strict=True):
        for j, shape in enumerate(shapes):
            colour = f"C{j}"
            ax.plot(truth[:, shape], "--", color=colour, alpha=0.6)
            ax.plot(take_weights[name][:, shape], color=colour, label=rig.names[shape])
        ax.set_title(f"{name} (solid) vs ground truth (dashed)")
        ax.set_xlabel("frame")
    axes[0].set_ylabel("weight")
    axes[0].legend(fontsize=7)
    save_figure(fig, path)


def _error_maps(rig, take_weights, clean, path):
    frame = len(clean) // 2
    names = list(take_weights)
    cols = 4
    fig, axes = plt.subplots(2, cols, figsize=(3 * cols, 7))
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    for ax, name in zip(axes.ravel(), names, strict=False):
        mesh = np.asarray(evaluate(rig, take_weights[name][frame]))
        error = per_vertex_distance(mesh, clean[frame]) * CM_TO_MM
        mapper = plot_vertex_scalar(
            ax,
            clean[frame],
            rig.faces,
            error,
            vmax=1.0,
            title=f"{name}\nmean {error.mean():.3f} mm",
        )
    fig.colorbar(mapper, ax=axes, shrink=0.6, label=f"error at frame {frame} (mm)")
    save_figure(fig, path)


if __name__ == "__main__":
    main()
