"""Speed of the inverse rig on the ict-quartic rig: ``inverse.QuarticCD`` against Algorithm 1
as published (issue 3, "Speed").

    python benchmarks/bench_inverse.py [--alpha 0.5] [--passes 5] [--reference-frames 3]
                                       [--out benchmarks/results/bench_inverse.md]

Targets: the rig evaluated at the 180 Live Link Face frames (retargeted onto ICT, missing
channels zero) plus Gaussian noise of variance 0.03 cm^2 per coordinate (seed 0). In one
process, ``inverse_reference.measure_reference`` times the NumPy float64 reference (the full
rig evaluated twice per coordinate) on the first frames and ``jit(vmap(solve))`` with
QuarticCD on all 180, and compares their weights. LinearCD and a one-pass QuarticCD are timed
the same way for context (the latter splits the QuarticCD time into a per-frame fixed cost and
a per-pass cost). Targets: <= 5 ms per frame and >= 100x the reference. A Markdown table is
printed and written to ``--out`` (atomically).
"""

from __future__ import annotations

import argparse
import os
import platform
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax import inverse
from canrig_jax.data import load_livelinkface
from canrig_jax.io import save_text
from canrig_jax.rig import BlendshapeRig, evaluate, ict_quartic_rig

try:  # as a module of the benchmarks package, or as a script from any directory
    from .inverse_reference import measure_reference, time_jax_solver
except ImportError:
    from inverse_reference import measure_reference, time_jax_solver

NOISE_VARIANCE_CM2 = 0.03
TARGET_SECONDS_PER_FRAME = 5e-3
TARGET_SPEEDUP = 100.0
DEFAULT_OUT = Path(__file__).parent / "results" / "bench_inverse.md"


def noisy_targets(rig: BlendshapeRig, seed: int = 0) -> np.ndarray:
    """(180, V, 3) float32: the rig at every Live Link frame + N(0, 0.03 cm^2) noise."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        weights = load_livelinkface().weights_for(rig.names, missing="zero")
    meshes = np.asarray(jax.jit(jax.vmap(evaluate, (None, 0)))(rig, jnp.asarray(weights)))
    noise = np.random.default_rng(seed).normal(0.0, np.sqrt(NOISE_VARIANCE_CM2), meshes.shape)
    return (meshes + noise).astype(np.float32)


def flop_estimate(problem: inverse.InverseProblem, passes: int) -> dict:
    """Per-frame multiply-add counts (2 FLOP each) of the dominant products.

    Coefficient space (``inverse.QuarticCD``): per coordinate one (m x P) block of the Gram
    matrix times a(w), 2 m P (m = the padded number of columns containing one weight), and a
    P x P matvec per pass for the history; per frame once the projection M^T (b - b0), 2 3V P.
    Reference: per coordinate two full-rig evaluations, 2 * 3V * P each.
    """
    k, n = problem.n_blendshapes, 3 * problem.n_vertices
    p = int(problem.gram.shape[0])
    m = int(problem.support.shape[1])
    per_pass = k * 2 * m * p + 2 * p * p
    return {
        "P": p,
        "m": m,
        "quartic_cd_per_pass": per_pass,
        "quartic_cd_per_frame": passes * per_pass + 2 * n * p,
        "reference_per_frame": passes * k * 2 * (2 * n * p),
    }


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--alpha", type=float, default=0.5, help="L1 weight (cm^2)")
    parser.add_argument("--passes", type=int, default=5, help="coordinate-descent passes")
    parser.add_argument(
        "--reference-frames", type=int, default=3, help="frames the NumPy reference solves"
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Markdown table path")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()[0]
    rig, _ = ict_quartic_rig(progress=False)
    targets = noisy_targets(rig)
    n_frames = targets.shape[0]

    result = measure_reference(
        rig, targets, alpha=args.alpha, passes=args.passes, n_reference_frames=args.reference_frames
    )
    problem = inverse.prepare(rig)
    linear_s, _ = time_jax_solver(
        problem, targets, inverse.LinearCD(alpha=args.alpha, passes=args.passes)
    )
    one_pass_s, _ = time_jax_solver(problem, targets, inverse.QuarticCD(alpha=args.alpha, passes=1))
    load_after = os.getloadavg()[0]

    numpy_s, jax_s = result["numpy_seconds_per_frame"], result["jax_seconds_per_frame"]
    per_pass_s = (jax_s - one_pass_s) / max(args.passes - 1, 1)
    fixed_s = one_pass_s - per_pass_s
    flops = flop_estimate(problem, args.passes)
    device = jax.devices()[0]
    rows = [
        (
            f"NumPy reference: Algorithm 1, full rig per coordinate, float64 "
            f"(fastest of the first {args.reference_frames} frames, one at a time)",
            numpy_s,
        ),
        (
            f"JAX QuarticCD, {args.passes} passes, float32 (`jit(vmap(solve))`, {n_frames} frames)",
            jax_s,
        ),
        (f"JAX LinearCD, {args.passes} passes, float32 (same, linear part only)", linear_s),
    ]
    lines = [
        f"# Inverse rig on ict-quartic: QuarticCD against Algorithm 1 as published "
        f"({rig.n_blendshapes} shapes, {flops['P'] - rig.n_blendshapes} correctives, "
        f"{rig.n_vertices:,} vertices)",
        "",
        f"{n_frames} Live Link Face frames through the rig + N(0, {NOISE_VARIANCE_CM2} cm^2) "
        f"noise (seed 0); alpha = {args.alpha}, decreasing-||b_i|| order, init 0. JAX: compiled "
        f"and warmed up, best of 3. JAX {jax.__version__} on {device.platform}, NumPy "
        f"{np.__version__}, {os.cpu_count()} CPU cores, "
        f"{platform.processor() or platform.machine()}; 1-min load average "
        f"{load_before:.2f} before, {load_after:.2f} after.",
        "",
        "| method | seconds/frame | frames/s | ratio (reference time / time) |",
        "| --- | ---: | ---: | ---: |",
    ]
    for label, seconds in rows:
        lines.append(
            f"| {label} | {seconds:.3g} | {1 / seconds:,.3g} | {numpy_s / seconds:,.0f}x |"
        )
    lines += [
        "",
        f"- Target <= 5 ms/frame: QuarticCD {jax_s * 1e3:.2f} ms/frame, "
        f"{_verdict(jax_s <= TARGET_SECONDS_PER_FRAME)}",
        f"- Target >= 100x: QuarticCD {result['speedup']:,.0f}x the reference, "
        f"{_verdict(result['speedup'] >= TARGET_SPEEDUP)}",
        f"- Max |w_numpy - w_jax| over the {args.reference_frames} reference frames: "
        f"{result['max_weight_difference']:.2e} (float64 against float32)",
        "",
        "Context:",
        "",
        f"- FLOP per frame (multiply-adds x 2, dominant products; P = K + correctives = "
        f"{flops['P']}, m = {flops['m']}): one QuarticCD pass in coefficient space = K Gram "
        f"blocks of 2 m P + one 2 P^2 = {flops['quartic_cd_per_pass'] / 1e6:.1f} MFLOP; "
        f"{args.passes} passes + "
        f"the projection M^T(b - b0) (2 x 3V x P, shared with the final objective) = "
        f"{flops['quartic_cd_per_frame'] / 1e6:.0f} MFLOP "
        f"({flops['quartic_cd_per_frame'] / jax_s / 1e9:.1f} GFLOP/s achieved); the reference "
        f"(2 full-rig evaluations of 2 x 3V x P per coordinate) = "
        f"{flops['reference_per_frame'] / 1e9:.1f} GFLOP "
        f"({flops['reference_per_frame'] / numpy_s / 1e9:.1f} GFLOP/s achieved), "
        f"{flops['reference_per_frame'] / flops['quartic_cd_per_frame']:.0f}x more.",
        f"- QuarticCD with 1 pass: {one_pass_s * 1e3:.2f} ms/frame, so about "
        f"{fixed_s * 1e3:.2f} ms/frame fixed (projection, final objective) and "
        f"{per_pass_s * 1e3:.2f} ms/frame per pass.",
        "",
    ]
    table = "\n".join(lines)
    print(table)
    save_text(args.out, table)
    print(f"wrote {args.out}")
    return table


if __name__ == "__main__":
    main()
