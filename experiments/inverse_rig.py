"""Racković et al. 2023's protocol on two heads: the ict-quartic rig and the MakeHuman hm08 head
(evaluation only) with correctives synthesised by ``synthesize_correctives``. Alpha sweep on
training poses, method comparison on the noisy Live Link take, convergence against the
minimum of the same objective, coordinate orders, and speed (batched, one frame per call,
the NumPy reference of Algorithm 1), all in one process.

    python experiments/inverse_rig.py --out experiments/results/inverse_rig
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from canrig_jax import inverse
from canrig_jax._io import save_results
from canrig_jax._metrics import CM_TO_MM, per_vertex_distance
from canrig_jax._provenance import experiment_command, provenance, record_command
from canrig_jax.data import load_livelinkface
from canrig_jax.inverse import roughness, summarize
from canrig_jax.papers.inverse_rig import (
    measure_reference,
    minimum,
    select_alpha,
    time_batched,
    time_single_frames,
)
from canrig_jax.render import plot_vertex_scalar, save_figure
from canrig_jax.rig import (
    UNIT_IN_CM,
    evaluate,
    evaluate_batch,
    ict_quartic_rig,
    makehuman_quartic_rig,
    random_sparse_poses,
)
from canrig_jax.watchdog import run_watched

NOISE_VARIANCE_CM2 = 0.03  # as in the paper


def paper_cd(alpha):
    """Algorithm 1 as published: 5 passes, no stopping rule, no Newton step."""
    return inverse.QuarticCD(alpha=alpha, passes=5, tol=0.0, newton=False)


SWEEP = {
    "quartic_cd": paper_cd,
    "quartic_cd_converged": lambda a: inverse.QuarticCD(alpha=a),
    "linear_cd": lambda a: inverse.LinearCD(alpha=a, passes=5, tol=0.0, newton=False),
    "cetinaslan": lambda a: inverse.Cetinaslan(alpha=a),
    "lmmm": lambda a: inverse.LMMM(alpha=a, iterations=50),
}
FIXED = {"seol": lambda a: inverse.Seol(), "joshi": lambda a: inverse.Joshi()}


def run(problem, targets, method):
    """(weights, seconds per frame, mean passes) of one batched solve over ``targets``."""
    seconds, _ = time_batched(problem, targets, method, repeats=1)
    solution = inverse.solve_sequence(problem, targets, method)
    return np.asarray(solution.weights), seconds, float(np.mean(solution.stats["steps"]))


def scores(rig, weights, clean, alpha_cm2, seconds=None):
    row = summarize(rig, weights, clean)
    return {
        "alpha": alpha_cm2,
        "rmse_mm": row["rmse_mean_mm"],
        "p95_mm": row["rmse_p95_mm"],
        "cardinality": row["cardinality"],
        "l1": row["l1"],
        "roughness": roughness(weights),
        "seconds_per_frame": seconds,
    }


def evaluate_case(name, rig, take, rng, args):
    """Sweep on training poses, chosen-alpha methods on the take, convergence, passes."""
    problem = inverse.prepare(rig)
    scale = UNIT_IN_CM[rig.units]  # cm per rig unit
    alphas_cm2 = [0.0, 0.5, 5.0] if args.quick else [0.0, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
    to_rig = lambda a: a / scale**2  # noqa: E731  alpha is in squared length units
    train = random_sparse_poses(rng, 20 if args.quick else args.train_poses, rig.names)
    noise = np.sqrt(NOISE_VARIANCE_CM2) / scale
    clean_train, clean = (
        np.asarray(evaluate_batch(rig, train)),
        np.asarray(evaluate_batch(rig, take)),
    )
    noisy_train = (clean_train + rng.normal(0, noise, clean_train.shape)).astype(np.float32)
    noisy = (clean + rng.normal(0, noise, clean.shape)).astype(np.float32)

    sweep, chosen = {}, {}
    for method, make in SWEEP.items():
        sweep[method] = []
        for alpha in alphas_cm2:
            weights, _, _ = run(problem, noisy_train, make(to_rig(alpha)))
            row = summarize(rig, weights, clean_train)
            sweep[method].append({"alpha": alpha, **row})
            print(f"[{name}] sweep {method} alpha={alpha} cm^2: {row}", flush=True)
        chosen[method] = select_alpha(sweep[method], method=method)["alpha"]
    chosen.update(seol=0.0, joshi=0.0)

    methods, take_weights, passes_taken = {}, {}, {}
    for method, make in {**SWEEP, **FIXED}.items():
        weights, seconds, steps = run(problem, noisy, make(to_rig(chosen[method])))
        take_weights[method], passes_taken[method] = weights, steps
        methods[method] = scores(rig, weights, clean, chosen[method], seconds)
        print(f"[{name}] test {method}: {methods[method]}", flush=True)

    # the minimum of QuarticCD's objective at its chosen alpha: SciPy float64 L-BFGS-B,
    # started from the converged solution (it can only go lower)
    alpha = to_rig(chosen["quartic_cd"])
    converged, _, converged_passes = run(problem, noisy, inverse.QuarticCD(alpha=alpha))
    start = time.perf_counter()
    lowest = np.stack(
        [minimum(problem, b, alpha, init=w) for b, w in zip(noisy, converged, strict=True)]
    )
    minimum_seconds = (time.perf_counter() - start) / len(noisy)
    best = scores(rig, lowest, clean, chosen["quartic_cd"], minimum_seconds)
    at_alpha = scores(rig, converged, clean, chosen["quartic_cd"])
    # the projected Gauss-Newton route to the same minimum, at the same alpha
    newton_weights, _, newton_iterations = run(problem, noisy, inverse.QuarticNewton(alpha=alpha))
    newton = scores(rig, newton_weights, clean, chosen["quartic_cd"])
    passes = {}
    for n in (1, 2, 5) if args.quick else (1, 2, 5, 10, 20, 50):
        method = inverse.QuarticCD(alpha=alpha, passes=n, tol=0.0, newton=False)
        weights, seconds, _ = run(problem, noisy, method)
        passes[str(n)] = scores(rig, weights, clean, chosen["quartic_cd"], seconds)
        print(f"[{name}] passes {n}: {passes[str(n)]}", flush=True)
    convergence = {
        "alpha": chosen["quartic_cd"],
        "cd_rmse_mm": at_alpha["rmse_mm"],
        "cd_5_passes_rmse_mm": passes["5"]["rmse_mm"],
        "minimum_rmse_mm": best["rmse_mm"],
        "passes_mean": converged_passes,
        "cd_cardinality": at_alpha["cardinality"],
        "minimum_cardinality": best["cardinality"],
        "minimum_seconds_per_frame": minimum_seconds,
        "newton_rmse_mm": newton["rmse_mm"],
        "newton_cardinality": newton["cardinality"],
        "newton_iterations_mean": newton_iterations,
    }
    print(f"[{name}] convergence: {convergence}", flush=True)
    truth = {"alpha": None, **scores(rig, take, clean, None)}
    return {
        "rig": rig,
        "problem": problem,
        "noisy": noisy,
        "clean": clean,
        "take": take,
        "sweep": sweep,
        "chosen": chosen,
        "methods": methods,
        "weights": take_weights,
        "passes": passes,
        "convergence": convergence,
        "truth": truth,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--quick", action="store_true", help="30 frames, 20 poses, 3 alphas")
    parser.add_argument("--train-poses", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    command = experiment_command(__file__, argv)
    rng = np.random.default_rng(args.seed)
    capture = load_livelinkface(args.data_dir)

    cases = {}
    rig, _ = ict_quartic_rig(args.data_dir, progress=False)
    mh_rig, mh_synthesis = makehuman_quartic_rig(args.data_dir)
    for name, case_rig in (("ict", rig), ("makehuman", mh_rig)):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
            take = capture.weights_for(case_rig.names, missing="zero")
        take = take[:30] if args.quick else take
        cases[name] = evaluate_case(name, case_rig, take, rng, args)

    ict = cases["ict"]
    problem, noisy = ict["problem"], ict["noisy"]
    alpha = ict["chosen"]["quartic_cd"]
    orderings = {}
    for order in inverse.ORDERS:
        method = inverse.QuarticCD(alpha=alpha, passes=5, tol=0.0, newton=False, order=order)
        weights, seconds, _ = run(problem, noisy, method)
        orderings[order] = scores(ict["rig"], weights, ict["clean"], alpha, seconds)
        print(f"order {order}: {orderings[order]}", flush=True)

    converged = inverse.QuarticCD(alpha=alpha)
    batched_s, _ = time_batched(problem, noisy, converged)
    single_s, _ = time_single_frames(problem, noisy, converged)
    warm_s, _ = time_single_frames(problem, noisy, converged, warm_start=True)
    newton = inverse.QuarticNewton(alpha=alpha)
    newton_batched_s, _ = time_batched(problem, noisy, newton)
    newton_single_s, _ = time_single_frames(problem, noisy, newton)
    newton_warm_s, _ = time_single_frames(problem, noisy, newton, warm_start=True)
    reference = measure_reference(
        ict["rig"], noisy, alpha=alpha, passes=5, n_reference_frames=1 if args.quick else 3,
        problem=problem,
    )  # fmt: skip
    timing = {
        "batched_ms_per_frame": batched_s * 1e3,
        "single_frame_ms": single_s * 1e3,
        "single_frame_warm_ms": warm_s * 1e3,
        "newton_batched_ms_per_frame": newton_batched_s * 1e3,
        "newton_single_frame_ms": newton_single_s * 1e3,
        "newton_single_frame_warm_ms": newton_warm_s * 1e3,
        "reference_ms_per_frame": reference["numpy_seconds_per_frame"] * 1e3,
        "paper_cd_batched_ms_per_frame": reference["jax_seconds_per_frame"] * 1e3,
        "reference_max_weight_difference": reference["max_weight_difference"],
        "note": "ict-quartic, converged QuarticCD (tol 1e-5, Newton steps) and QuarticNewton "
        "(tol 1e-5) at the chosen alpha; "
        "reference = the NumPy Algorithm 1 (5 passes), one frame at a time; the machine's 2 "
        "CPU cores were shared with other jobs",
    }
    print(f"timing: {timing}", flush=True)

    results = {
        "cases": {
            name: {m: {k: v for k, v in row.items()} for m, row in case["methods"].items()}
            for name, case in cases.items()
        },
        "convergence": {name: case["convergence"] for name, case in cases.items()},
        "timing": timing,
        "sweep": {name: case["sweep"] for name, case in cases.items()},
        "passes": {name: case["passes"] for name, case in cases.items()},
        "ground_truth": {name: case["truth"] for name, case in cases.items()},
        "orderings": orderings,
        "reference": reference,
        "makehuman_synthesis": mh_synthesis,
        "protocol": {
            "test_frames": len(ict["take"]),
            "train_poses": 20 if args.quick else args.train_poses,
            "noise_variance_cm2": NOISE_VARIANCE_CM2,
            "alpha_units": "cm^2 (divided by (cm per rig unit)^2 for the decimetre head)",
            "alpha_rule": "largest alpha with training mean RMSE within 5% of the method's best",
            "cardinality_tol": inverse.CARDINALITY_TOL,
            "quartic_cd": "Algorithm 1 as published: 5 passes, decreasing order",
            "quartic_cd_converged": "QuarticCD defaults: tol 1e-5 relative, Newton steps",
            "quartic_newton": "QuarticNewton defaults (tol 1e-5) at quartic_cd's alpha",
            "minimum": "SciPy float64 L-BFGS-B from the converged solution",
        },
        "provenance": provenance(command),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    # keeps the keys and table sections that sibling scripts (inverse_rig_*.py) wrote
    save_results(args.out, results, _table(cases, orderings, timing, reference))
    if not args.quick:
        record_command(args.out, command)
    for name, case in cases.items():
        _tradeoff_plot(case["sweep"], case["chosen"], args.out / f"tradeoff_{name}.png")
        _weight_curves(case, args.out / f"weight_curves_{name}.png")
        _error_maps(case, args.out / f"error_maps_{name}.png")
    print((args.out / "table.md").read_text())
    print(f"wrote {args.out}")
    return results


COLUMNS = ("alpha", "rmse_mm", "p95_mm", "cardinality", "l1", "roughness", "seconds_per_frame")


def _row(name, values):
    cells = ["–" if values.get(k) is None else f"{values[k]:.4g}" for k in COLUMNS]
    return f"| {name} | " + " | ".join(cells) + " |\n"


def _table(cases, orderings, timing, reference):
    head = "| method | " + " | ".join(COLUMNS) + " |\n" + "|---" * (len(COLUMNS) + 1) + "|\n"
    text = ""
    for name, case in cases.items():
        text += (
            f"## {name}: methods on the noisy Live Link take (Table 3 layout; alpha in cm^2)\n\n"
        )
        text += head + _row("ground truth", case["truth"])
        text += "".join(_row(m, values) for m, values in case["methods"].items())
        c = case["convergence"]
        text += (
            f"\nConvergence at alpha = {c['alpha']} cm^2: 5-pass CD "
            f"{c['cd_5_passes_rmse_mm']:.4g} mm, converged CD {c['cd_rmse_mm']:.4g} mm "
            f"({c['passes_mean']:.1f} passes on average), "
            f"minimum (L-BFGS-B, float64) {c['minimum_rmse_mm']:.4g} mm; cardinality "
            f"{c['cd_cardinality']:.4g} vs {c['minimum_cardinality']:.4g}; QuarticNewton "
            f"(projected Gauss-Newton, tol 1e-5) {c['newton_rmse_mm']:.4g} mm in "
            f"{c['newton_iterations_mean']:.1f} iterations on average, cardinality "
            f"{c['newton_cardinality']:.4g}.\n\n"
        )
        text += f"### {name}: QuarticCD against the number of passes (decreasing order)\n\n" + head
        text += "".join(_row(f"{n} passes", values) for n, values in case["passes"].items())
        text += "\n"
    text += "## ict: coordinate orders, QuarticCD 5 passes (Table 8 analog)\n\n" + head
    text += "".join(_row(name, values) for name, values in orderings.items())
    text += (
        "\n## Speed on ict-quartic (one process; CPU shared with other jobs)\n\n"
        "| converged QuarticCD, batched over the take | one frame per call (Stream) | "
        "one frame, warm-started | NumPy Algorithm 1 (5 passes) per frame | 5-pass JAX batched |\n"
        "|---|---|---|---|---|\n"
        f"| {timing['batched_ms_per_frame']:.3g} ms | {timing['single_frame_ms']:.3g} ms | "
        f"{timing['single_frame_warm_ms']:.3g} ms | {timing['reference_ms_per_frame']:.4g} ms | "
        f"{timing['paper_cd_batched_ms_per_frame']:.3g} ms |\n\n"
        f"Ratios to the NumPy reference (same process): converged batched "
        f"{timing['reference_ms_per_frame'] / timing['batched_ms_per_frame']:,.0f}x, "
        f"converged one frame per call "
        f"{timing['reference_ms_per_frame'] / timing['single_frame_ms']:,.0f}x, 5-pass batched "
        f"{reference['speedup']:,.0f}x (weights agree to "
        f"{reference['max_weight_difference']:.2g}).\n\n"
        "QuarticNewton (same alpha): batched "
        f"{timing['newton_batched_ms_per_frame']:.3g} ms, one frame per call "
        f"{timing['newton_single_frame_ms']:.3g} ms, warm-started "
        f"{timing['newton_single_frame_warm_ms']:.3g} ms per frame.\n"
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
        ax.set_title(f"training poses: {label} error vs cardinality", fontsize=10)
    axes[0].legend(title="dot size: alpha; ring: chosen", fontsize=8, title_fontsize=8)
    save_figure(fig, path)


def _weight_curves(case, path, methods=("quartic_cd_converged", "joshi", "cetinaslan")):
    rig, truth = case["rig"], case["take"]
    shapes = np.argsort(-truth.max(axis=0))[:5]
    fig, axes = plt.subplots(1, len(methods), figsize=(5 * len(methods), 3.5), sharey=True)
    for ax, name in zip(axes, methods, strict=True):
        for j, shape in enumerate(shapes):
            ax.plot(truth[:, shape], "--", color=f"C{j}", alpha=0.6)
            ax.plot(case["weights"][name][:, shape], color=f"C{j}", label=rig.names[shape])
        ax.set_title(f"{name} (solid) vs ground truth (dashed)", fontsize=9)
        ax.set_xlabel("frame")
    axes[0].set_ylabel("weight")
    axes[0].legend(fontsize=7)
    save_figure(fig, path)


def _error_maps(case, path):
    rig, clean = case["rig"], case["clean"]
    frame = len(clean) // 2
    names = list(case["weights"])
    cols = 4
    fig, axes = plt.subplots(2, cols, figsize=(3 * cols, 7))
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    for ax, name in zip(axes.ravel(), names, strict=False):
        mesh = np.asarray(evaluate(rig, case["weights"][name][frame]))
        error = per_vertex_distance(mesh, clean[frame]) * (UNIT_IN_CM[rig.units] * CM_TO_MM)
        mapper = plot_vertex_scalar(
            ax, clean[frame], rig.faces, error, vmax=1.0,
            title=f"{name}\nmean {error.mean():.3f} mm",
        )  # fmt: skip
    fig.colorbar(mapper, ax=axes, shrink=0.6, label=f"error at frame {frame} (mm)")
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
