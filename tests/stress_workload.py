"""The compiled solves users run, many times over, as one process: the stress test's workload.

Run by ``tests/test_deadlock.py`` (in a subprocess with a timeout, idle and beside a CPU hog)
and by ``nox -s stress`` (200 calls each). On the real ICT face (cm): fitted pose A to B on a
``LocalFitRig`` (the README's: 59 basis offsets, 600 patches, 200 random handles) and on the
trained CANRig of ``experiments/results/canrig_workflows``, dialogue replacement with fits
(the fit under ``vmap``), QuarticNewton one frame per call, every inverse method on a batched
take, a batch of CANRig-PBS local-prior edits with the gradient in the ridge (its training
path), and the WPSE solves. Each phase prints its time. A hang ends the process through
``canrig_jax.watchdog`` with a stack dump (exit status 70), never silence.

    python tests/stress_workload.py --calls 200 [--data-dir D] [--phases local,network,...]
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

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
from canrig_jax.rig import exclusive_pairs, ict_quartic_rig, random_sparse_poses
from canrig_jax.watchdog import watchdog
from canrig_jax.wpse._pse import solve_coefficients
from canrig_jax.wpse._sigma import loo_error

ROOT = Path(__file__).resolve().parents[1]
NETWORK = ROOT / "experiments/results/canrig_workflows/model/checkpoint.eqx"
PHASES = ("local", "network", "dialogue", "newton", "methods", "pbs", "wpse")


def _fits(rig, frames, calls, rng, label):
    """``calls`` fitted A-to-B calls: random capture-frame pairs, three sets of 200 random
    handles in turn (a new set may compile new block widths; three keep the run short)."""
    sets = [rig.handles(rng.choice(rig.n_vertices, 200, replace=False)) for _ in range(3)]
    for i in range(calls):
        a, b = frames[rng.choice(len(frames), 2, replace=False)]
        solution = pose_a_to_b(rig, sets[i % 3], a, b, 2.0, 3.0, fit=True)
        if not np.isfinite(float(solution.error)):
            raise SystemExit(f"{label}: fit {i} returned a non-finite error")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--phases", default=",".join(PHASES))
    parser.add_argument("--watchdog", type=float, default=120.0, help="seconds without progress")
    args = parser.parse_args(argv)
    phases = args.phases.split(",")
    rng = np.random.default_rng(0)
    with watchdog(args.watchdog, "stress workload") as dog:
        start = time.perf_counter()

        def done(phase):
            dog.progress(phase)
            print(f"{phase}: {time.perf_counter() - start:.1f} s", flush=True)

        rig, _ = ict_quartic_rig(args.data_dir, parts=FACE, progress=False)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
            weights = load_livelinkface(args.data_dir).weights_for(rig.names)
        frames = np.asarray(evaluate_poses(rig, weights))  # (180, V, 3)
        done("setup")
        if "local" in phases or "dialogue" in phases:
            poses = random_sparse_poses(np.random.default_rng(1), 400, rig.names)
            basis, _ = pbs_basis(rig.neutral, evaluate_poses(rig, poses), 60)
            layout = patch_layout(rig.neutral, rig.faces, 600, rings=3)
            local = NeuralRig(local_fit_rig(layout, basis, ridge=1e-4), rig.neutral, rig.faces)
            done("local rig built")
        if "local" in phases:
            _fits(local, frames, args.calls, rng, "LocalFitRig")
            done(f"LocalFitRig: {args.calls} fitted A-to-B calls")
        if "network" in phases:
            model, _ = load_model(NETWORK, rig.neutral)
            network = NeuralRig(model, rig.neutral, rig.faces)
            _fits(network, frames, args.calls, rng, "CANRig")
            done(f"CANRig: {args.calls} fitted A-to-B calls")
        if "dialogue" in phases:
            mouth = local.handles(rng.choice(local.n_vertices, 60, replace=False))
            clip = frames[40:48]
            dialogue_replacement(local, clip, frames[100:108], mouth, 2.0, 3.0, fit=True)
            done("dialogue replacement, fitted, 8 frames (vmap)")
        if "newton" in phases or "methods" in phases:
            problem = inverse.prepare(rig)
            done("inverse problem prepared")
        if "newton" in phases:
            method = inverse.QuarticNewton(alpha=0.5)
            for i in range(args.calls):
                target = frames[i % len(frames)]
                if not np.all(np.isfinite(inverse.solve(problem, target, method).weights)):
                    raise SystemExit(f"QuarticNewton: frame {i} gave non-finite weights")
            done(f"QuarticNewton: {args.calls} one-frame solves")
        if "methods" in phases:
            # every method that factorises or decomposes (the closed forms Seol and Joshi do
            # not; LinearCD is QuarticCD's code on the linear part, Cetinaslan LMMM's start)
            skip = (inverse.Seol, inverse.Joshi, inverse.LinearCD, inverse.Cetinaslan)
            for cls in (c for c in inverse.METHODS if c not in skip):
                if cls is inverse.Constrained:  # a wrapper: the exclusive pairs of this rig
                    pairs = tuple(exclusive_pairs(rig.names))
                    method = cls(inverse.QuarticNewton(), exclusive=pairs)
                else:
                    method = cls(maxiter=20) if cls is inverse.JaxoptLBFGSB else cls()
                # batched (vmap): where a batched LAPACK call could appear; a warm start is a
                # scan over one frame's solve, one matrix per call by construction
                inverse.solve_sequence(problem, frames[:12], method)
            done(f"{len(inverse.METHODS) - len(skip)} inverse methods, batched")
        if "pbs" in phases:
            # CANRig-PBS with the local prior (untrained: the compiled path, not its quality)
            poses = random_sparse_poses(np.random.default_rng(2), 60, rig.names)
            basis, _ = pbs_basis(rig.neutral, evaluate_poses(rig, poses), 18)
            layout = patch_layout(rig.neutral, rig.faces, 200, rings=2)
            handles = rng.choice(rig.n_vertices, 120, replace=False)
            seeds = jnp.asarray(rig.neutral[layout.seeds])
            distance = jnp.linalg.norm(seeds[:, None] - rig.neutral[handles][None], axis=-1)
            mask = influence_mask(distance, 2.0, 3.0)
            model = PerPatchPBS(rig.neutral, 200, 17, local_prior=True, key=jax.random.key(0))
            queries, base = model.encode_patches(seeds), patch_means(layout, rig.neutral)
            rest, handle_basis = jnp.asarray(rig.neutral[handles]), basis[:, handles]
            edits = jnp.asarray(frames[:64, handles] - rig.neutral[handles])

            @eqx.filter_jit
            def predict(model, edits):
                one = lambda d: model(queries, base, rest, rest, d, mask, None, handle_basis)
                return jax.vmap(one)(edits)

            loss = eqx.filter_grad(lambda model, edits: jnp.sum(predict(model, edits) ** 2))
            for _ in range(max(1, args.calls // 20)):
                jax.block_until_ready(predict(model, edits))
                jax.block_until_ready(eqx.filter(loss(model, edits[:8]), eqx.is_array))
            done("CANRig-PBS local prior: batches of 64 edits and the training gradient")
        if "wpse" in phases:
            metric = jnp.asarray(rng.uniform(0.5, 1.5, (300, rig.n_blendshapes)), jnp.float32)
            poses = jnp.asarray(weights[::30], jnp.float32)  # 6 sculpted poses
            edits = jnp.asarray(rng.normal(0, 0.1, (300, poses.shape[0], 3)), jnp.float32)
            for _ in range(max(1, args.calls // 20)):
                jax.block_until_ready(solve_coefficients(metric, poses, edits, 1.0, 1e-6))
                jax.block_until_ready(jax.grad(lambda s: loo_error(metric, poses, edits, s))(1.0))
            done("WPSE: per-vertex RBF solves and the LOO gradient")
    print("ok", flush=True)


if __name__ == "__main__":
    main()
