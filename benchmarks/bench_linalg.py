"""The fits' speed with one matrix per LAPACK call (``canrig_jax._linalg``) against the batched
LAPACK calls they made before (``CANRIG_BENCH_BATCHED_LAPACK=1``), in one run.

Each side runs in its own process (the flag is read at import), alternately, ``--rounds``
times, each under a timeout: the batched reference can deadlock (XLA's CPU thread pool; see
``canrig_jax._linalg``), and a process that hangs is reported as such, not waited for. A row's
figure is the lowest median (of three, over its calls) of the fastest round; the ratio is
new / reference (below 1: faster). On the real ICT face (cm), warm (compiled before timing):

- pose A to B, fitted, 200 random handles / 2 cm: the trained CANRig
  (``experiments/results/canrig_workflows``) and the README's ``LocalFitRig`` (59 offsets,
  600 patches, ridge 1e-4), 10 calls over capture-frame pairs, one handle set;
- dialogue replacement, fitted, on that ``LocalFitRig``: 8 frames in one call, per frame;
- QuarticNewton (alpha 0.5): one frame per call (30 calls) and a 60-frame take batched;
- LMMM (whose majoriser needs the largest eigenvalue): a 12-frame take batched, per frame;
- CANRig-PBS with the local prior (untrained weights: the compiled path): 64 edits batched;
- WPSE: the per-vertex RBF coefficients of 300 vertices and 6 sculpted poses.

    python benchmarks/bench_linalg.py [--rounds 2] [--timeout 300]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks/results/bench_linalg.md"
NETWORK = ROOT / "experiments/results/canrig_workflows/model/checkpoint.eqx"


def _median_ms(fn, calls: int, repeats: int = 3) -> float:
    """The lowest of ``repeats`` medians of ``calls`` warm calls ``fn(i)``, in ms."""
    import jax
    import numpy as np

    jax.block_until_ready(fn(0))  # compile
    medians = []
    for _ in range(repeats):
        seconds = []
        for i in range(calls):
            start = time.perf_counter()
            jax.block_until_ready(fn(i))
            seconds.append(time.perf_counter() - start)
        medians.append(np.median(seconds))
    return float(min(medians) * 1e3)


def measure():
    """Yields (row, milliseconds per call or frame) in this process's lowering; the rows
    that hung the batched reference most often (the LocalFitRig fits) come last."""
    import warnings

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    from canrig_jax import inverse
    from canrig_jax.canrig import (
        NeuralRig,
        dialogue_replacement,
        influence_mask,
        load_model,
        pose_a_to_b,
    )
    from canrig_jax.canrig._data import evaluate_poses
    from canrig_jax.data import FACE, load_livelinkface
    from canrig_jax.pbs import PerPatchPBS, local_fit_rig, patch_layout, pbs_basis
    from canrig_jax.pbs._model import patch_means
    from canrig_jax.rig import ict_quartic_rig, random_sparse_poses
    from canrig_jax.wpse._pse import solve_coefficients

    rig, _ = ict_quartic_rig(parts=FACE, progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        weights = load_livelinkface().weights_for(rig.names)
    frames = np.asarray(evaluate_poses(rig, weights))
    rng = np.random.default_rng(0)
    pairs = [rng.choice(len(frames), 2, replace=False) for _ in range(11)]
    index = rng.choice(rig.n_vertices, 200, replace=False)

    model, _ = load_model(NETWORK, rig.neutral)
    network = NeuralRig(model, rig.neutral, rig.faces)
    handles = network.handles(index)

    def fit(rig_, i):
        a, b = frames[pairs[i]]
        return pose_a_to_b(rig_, handles, a, b, 2.0, 3.0, fit=True).shape

    yield "pose A to B, fitted, CANRig", _median_ms(lambda i: fit(network, i), 10)
    poses = random_sparse_poses(np.random.default_rng(1), 400, rig.names)
    problem = inverse.prepare(rig)
    newton = inverse.QuarticNewton(alpha=0.5)
    yield (
        "QuarticNewton, one frame per call",
        _median_ms(lambda i: inverse.solve(problem, frames[i], newton).weights, 30),
    )
    yield (
        "QuarticNewton, 60 frames batched, per frame",
        (
            _median_ms(lambda i: inverse.solve_sequence(problem, frames[:60], newton).weights, 3)
            / 60
        ),
    )
    lmmm = inverse.LMMM()
    yield (
        "LMMM, 12 frames batched, per frame",
        (_median_ms(lambda i: inverse.solve_sequence(problem, frames[:12], lmmm).weights, 3) / 12),
    )

    basis18, _ = pbs_basis(rig.neutral, evaluate_poses(rig, poses[:60]), 18)
    layout200 = patch_layout(rig.neutral, rig.faces, 200, rings=2)
    seeds = jnp.asarray(rig.neutral[layout200.seeds])
    handle_index = index[:120]
    rest = jnp.asarray(rig.neutral[handle_index])
    mask = influence_mask(jnp.linalg.norm(seeds[:, None] - rest[None], axis=-1), 2.0, 3.0)
    pbs = PerPatchPBS(rig.neutral, 200, 17, local_prior=True, key=jax.random.key(0))
    queries, base = pbs.encode_patches(seeds), patch_means(layout200, rig.neutral)
    handle_basis = basis18[:, handle_index]
    edits = jnp.asarray(frames[:, handle_index] - rig.neutral[handle_index])

    @eqx.filter_jit
    def predict(model, edits):
        one = lambda d: model(queries, base, rest, rest, d, mask, None, handle_basis)  # noqa: E731
        return jax.vmap(one)(edits)

    yield (
        "CANRig-PBS local prior, 64 edits batched",
        _median_ms(lambda i: predict(pbs, edits[i : i + 64]), 10),
    )
    metric = jnp.asarray(rng.uniform(0.5, 1.5, (300, rig.n_blendshapes)), jnp.float32)
    sculpted = jnp.asarray(weights[::30], jnp.float32)
    displacements = jnp.asarray(rng.normal(0, 0.1, (300, sculpted.shape[0], 3)), jnp.float32)
    yield (
        "WPSE RBF coefficients, 300 vertices",
        _median_ms(
            lambda i: solve_coefficients(metric, sculpted, displacements, 1.0 + 0.01 * i, 1e-6), 10
        ),
    )
    basis, _ = pbs_basis(rig.neutral, evaluate_poses(rig, poses), 60)
    layout = patch_layout(rig.neutral, rig.faces, 600, rings=3)
    local = NeuralRig(local_fit_rig(layout, basis, ridge=1e-4), rig.neutral, rig.faces)
    yield "pose A to B, fitted, LocalFitRig", _median_ms(lambda i: fit(local, i), 10)
    yield (
        "dialogue replacement, fitted, LocalFitRig, per frame",
        (
            _median_ms(
                lambda i: dialogue_replacement(
                    local, frames[40:48], frames[100 + i : 108 + i], handles, 2.0, 3.0, fit=True
                ),
                3,
            )
            / 8
        ),
    )


def _child(batched: bool, timeout: float) -> tuple[dict[str, float], bool]:
    """(rows timed, whether the process finished before ``timeout``)."""
    env = dict(os.environ, CANRIG_BENCH_BATCHED_LAPACK="1" if batched else "0")
    command = [sys.executable, __file__, "--child"]
    try:
        run = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)
        output, finished = run.stdout, True
        if run.returncode != 0:
            raise RuntimeError(f"bench_linalg (batched={batched}) failed:\n{run.stderr[-3000:]}")
    except subprocess.TimeoutExpired as expired:  # the rows timed before the hang count
        output, finished = expired.stdout or "", False
        output = output.decode() if isinstance(output, bytes) else output
    rows = dict(json.loads(line) for line in output.splitlines() if line.startswith("["))
    return rows, finished


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per process")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        for row in measure():
            print(json.dumps(row), flush=True)
        return
    best: dict[bool, dict[str, float]] = {False: {}, True: {}}
    hung = {False: 0, True: 0}
    for round_ in range(args.rounds):
        for batched in (True, False):
            print(f"round {round_ + 1}, {'batched' if batched else 'one matrix'} ...", flush=True)
            rows, finished = _child(batched, args.timeout)
            hung[batched] += not finished
            for name, ms in rows.items():
                best[batched][name] = min(ms, best[batched].get(name, float("inf")))
    import jax

    lines = [
        "Fits with one matrix per LAPACK call (now) against batched LAPACK calls (before), "
        f"best of {args.rounds} alternating processes each, median ms per call (or frame)",
        f"{platform.machine()}, {os.cpu_count()} CPUs, load average "
        f"{os.getloadavg()[0]:.1f} at the end, jax {jax.__version__}",
        "",
        "| fit | one matrix per call, ms | batched (before), ms | ratio |",
        "|---|---|---|---|",
    ]
    for name, ms in best[False].items():
        before = best[True].get(name)
        ratio = f"{ms / before:.2f}" if before else "-"
        before_text = f"{before:.2f}" if before else "hung"
        lines.append(f"| {name} | {ms:.2f} | {before_text} | {ratio} |")
    lines += [
        "",
        f"processes that hung past {args.timeout:g} s: one matrix per call {hung[False]} of "
        f"{args.rounds}, batched {hung[True]} of {args.rounds}",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    from canrig_jax._io import save_text

    save_text(OUT, text)


if __name__ == "__main__":
    main()
