"""L-BFGS-B (``inverse.JaxoptLBFGSB``) over a take, batched against one frame at a time, on the
ict-quartic rig, every ratio measured in this run.

    python benchmarks/bench_lbfgsb.py [--frames 60] [--alpha 5.0] [--plain-frames 40]
                                      [--out benchmarks/results/bench_lbfgsb.md]

Targets: the rig at the first ``--frames`` Live Link Face frames plus N(0, 0.03 cm^2) noise
(seed 0). Timed, compiled and warmed up first, the best of three interleaved rounds each (the
CPU is shared): ``solve`` called once per frame (the reference: the total over the frames, per
frame; and the median frame, as ``inverse_rig.time_single_frames`` reports it), and
``solve_sequence`` over the take (one call; the library runs jaxopt's frames one after another
under ``vmap``, ``sequential_vmap``). For the record, jaxopt's solver under a plain
``jax.vmap`` (how it was batched before) on the first ``--plain-frames`` frames, in a
subprocess under ``--timeout``: its cost per frame grows with the batch (with ``--plain-only``
on this project's 2 cores, idle: 20 ms per frame for 10 frames, 1,250 ms for 40; under load
88, 343 and 5,670 ms for 10, 20 and 40), so only ``--plain-frames`` frames are timed. The
goal: batched costs about what its frames cost one by one. The iterations and result codes of
each frame are compared too (the same work either way). A Markdown table is printed and
written to ``--out`` (atomically).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from canrig_jax import inverse
from canrig_jax._io import save_text
from canrig_jax.data import load_livelinkface
from canrig_jax.rig import BlendshapeRig, evaluate_batch, ict_quartic_rig

DEFAULT_OUT = Path(__file__).parent / "results" / "bench_lbfgsb.md"
NOISE_VARIANCE_CM2 = 0.03


def noisy_targets(rig: BlendshapeRig, frames: int, seed: int = 0) -> np.ndarray:
    """(frames, V, 3) float32: the rig at the first Live Link frames + N(0, 0.03 cm^2) noise."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        weights = load_livelinkface().weights_for(rig.names, missing="zero")[:frames]
    meshes = np.asarray(evaluate_batch(rig, weights))
    noise = np.random.default_rng(seed).normal(0.0, np.sqrt(NOISE_VARIANCE_CM2), meshes.shape)
    return (meshes + noise).astype(np.float32)


def result_names(result) -> list[str]:
    """The ``optimistix.RESULTS`` member name of each frame of a (batched) result."""
    by_index = {int(item._value): name for name, item in optx.RESULTS._name_to_item.items()}
    return [by_index[int(i)] for i in np.atleast_1d(np.asarray(result._value))]


def one_by_one(problem, targets, method, repeats: int = 2) -> dict:
    """``solve`` per frame, each waited for: best-of-``repeats`` total and median frame."""
    jax.block_until_ready(inverse.solve(problem, targets[0], method).weights)  # compile
    best_total, best_median, solutions = np.inf, np.inf, []
    for _ in range(repeats):
        seconds, solutions = [], []
        for target in targets:
            start = time.perf_counter()
            solution = inverse.solve(problem, target, method)
            jax.block_until_ready(solution.weights)
            seconds.append(time.perf_counter() - start)
            solutions.append(solution)
        best_total = min(best_total, float(np.sum(seconds)))
        best_median = min(best_median, float(np.median(seconds)))
    return {
        "ms_per_frame": best_total / len(targets) * 1e3,
        "median_ms": best_median * 1e3,
        "steps": np.array([int(s.stats["steps"]) for s in solutions]),
        "results": [result_names(s.result)[0] for s in solutions],
        "weights": np.stack([np.asarray(s.weights) for s in solutions]),
    }


def batched(problem, targets, method, repeats: int = 2) -> dict:
    """``solve_sequence`` over the take: best-of-``repeats`` seconds, per frame."""
    targets = jnp.asarray(targets)
    solution = inverse.solve_sequence(problem, targets, method)  # compile
    jax.block_until_ready(solution.weights)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(inverse.solve_sequence(problem, targets, method).weights)
        best = min(best, time.perf_counter() - start)
    return {
        "ms_per_frame": best / targets.shape[0] * 1e3,
        "steps": np.asarray(solution.stats["steps"]),
        "results": result_names(solution.result),
        "weights": np.asarray(solution.weights),
    }


def _plain_vmap_only(frames: int, alpha: float) -> str:
    """jaxopt's L-BFGS-B under a plain ``jax.vmap`` (the library's settings and objective),
    ms per frame as JSON; run in a subprocess by ``main``."""
    import jaxopt

    rig, _ = ict_quartic_rig(progress=False)
    problem = inverse.prepare(rig)
    targets = jnp.asarray(noisy_targets(rig, frames))
    method = inverse.JaxoptLBFGSB(alpha=alpha)

    @jax.jit
    def plain(targets):
        def one(target):
            offset = (target - problem.neutral).reshape(-1)
            projection, offset_sq = problem.projection(offset), offset @ offset
            solver = jaxopt.LBFGSB(
                fun=lambda w: problem.objective(w, projection, offset_sq, method.alpha),
                maxiter=method.maxiter,
                tol=method.tol,
                stop_if_linesearch_fails=True,
            )
            init = jnp.zeros(problem.n_blendshapes, offset.dtype)
            params, state = solver.run(init, bounds=(init, jnp.full_like(init, method.upper)))
            return params, state.iter_num

        return jax.vmap(one)(targets)

    jax.block_until_ready(plain(targets))  # compile
    start = time.perf_counter()
    _, steps = jax.block_until_ready(plain(targets))
    seconds = time.perf_counter() - start
    text = json.dumps({"ms_per_frame": seconds / frames * 1e3, "steps": float(steps.mean())})
    print(text)
    return text


def _plain_vmap(frames: int, alpha: float, timeout: float) -> dict | None:
    command = [sys.executable, __file__, "--plain-only", "--plain-frames", str(frames)]
    command += ["--alpha", str(alpha)]
    try:
        done = subprocess.run(command, check=True, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--alpha", type=float, default=5.0, help="L1 weight (cm^2)")
    parser.add_argument(
        "--plain-frames", type=int, default=40, help="frames of the plain-vmap row (0: skip)"
    )
    parser.add_argument("--timeout", type=float, default=600.0, help="plain-vmap row, seconds")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Markdown table path")
    parser.add_argument("--plain-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.plain_only:
        return _plain_vmap_only(args.plain_frames, args.alpha)

    load_before = os.getloadavg()[0]
    rig, _ = ict_quartic_rig(progress=False)
    problem = inverse.prepare(rig)
    targets = noisy_targets(rig, args.frames)
    method = inverse.JaxoptLBFGSB(alpha=args.alpha)
    single, batch = one_by_one(problem, targets, method), batched(problem, targets, method)
    for _ in range(2):  # interleaved rounds, the best of each: the CPU is shared
        again = one_by_one(problem, targets, method, repeats=1)
        single["ms_per_frame"] = min(single["ms_per_frame"], again["ms_per_frame"])
        single["median_ms"] = min(single["median_ms"], again["median_ms"])
        batch["ms_per_frame"] = min(
            batch["ms_per_frame"], batched(problem, targets, method, repeats=1)["ms_per_frame"]
        )
    plain = _plain_vmap(args.plain_frames, args.alpha, args.timeout) if args.plain_frames else None
    load_after = os.getloadavg()[0]

    reference = single["ms_per_frame"]
    rows = [
        ("`solve`, one frame per call (reference: total / frames)", reference),
        ("`solve`, one frame per call, median frame", single["median_ms"]),
        ("`solve_sequence` over the take (sequential_vmap inside)", batch["ms_per_frame"]),
    ]
    if plain is not None:
        rows.append(
            (f"jaxopt under a plain `jax.vmap`, first {args.plain_frames} frames (before)",
             plain["ms_per_frame"])
        )  # fmt: skip
    same_steps = np.array_equal(single["steps"], batch["steps"])
    counts = collections.Counter(batch["results"])
    lines = [
        f"# L-BFGS-B over a take on ict-quartic ({rig.n_blendshapes} shapes, "
        f"{rig.n_vertices:,} vertices)",
        "",
        f"{len(targets)} Live Link Face frames through the rig + N(0, 0.03 cm^2) noise (seed 0); "
        f"`JaxoptLBFGSB(alpha={args.alpha})` (gram objective, maxiter {method.maxiter}, tol "
        f"{method.tol}), init 0. Every row in this one run, compiled and warmed up first; JAX "
        f"{jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPU cores; 1-min "
        f"load average {load_before:.2f} before, {load_after:.2f} after (shared cores).",
        "",
        "| what | ms per frame | ratio to one frame per call |",
        "| --- | ---: | ---: |",
    ]
    lines += [f"| {label} | {ms:.3g} | {ms / reference:.2f}x |" for label, ms in rows]
    lines += [
        "",
        f"- Iterations per frame: mean {batch['steps'].mean():.1f}, max {batch['steps'].max()} "
        f"batched; mean {single['steps'].mean():.1f} one by one; the same on every frame: "
        f"{same_steps}. Largest weight difference batched vs one by one: "
        f"{np.abs(batch['weights'] - single['weights']).max():.1e}.",
        f"- Result codes (batched): {dict(counts)}; one by one: "
        f"{dict(collections.Counter(single['results']))}. `stagnation`: the line search "
        "failed before the projected-gradient tolerance (the run stops there).",
    ]
    if plain is not None:
        lines.append(
            f"- The plain `jax.vmap` ran {plain['steps']:.1f} iterations per frame on average; "
            f"it costs {plain['ms_per_frame'] / batch['ms_per_frame']:.0f}x the library's "
            "batched call per frame."
        )
    elif args.plain_frames:
        lines.append(f"- The plain `jax.vmap` row did not finish within {args.timeout:.0f} s.")
    table = "\n".join(lines) + "\n"
    print(table)
    save_text(args.out, table)
    print(f"wrote {args.out}")
    return table


if __name__ == "__main__":
    main()
