"""The workload of the multi-process tests and of ``nox -s distributed``: run it as one
process, or as N under ``canrig launch -n N`` (or srun), and compare what it writes.

``python tests/distributed_worker.py run --out DIR``: ``distributed.initialize()`` from the
environment, then, on real data, a few steps of each trainer (CANRig on a tiny ict-quartic
set, CANRig-PBS on 40 patches of the ICT face, RigAnyFace on one decimated ICT identity; all
data-parallel over every process's device), the quartic inverse rig of an odd-length take
shared across processes (``solve_sequence(..., across_processes=True)``) and the packaged
RigAnyFace auto-rig of two heads shared across processes (``auto_rig_heads``). Process 0
writes ``DIR/result.npz`` (parameters, losses, weights, rigs) and ``DIR/timing.json``.

``python tests/distributed_worker.py wait``: initialize, then all-reduce a small array every
0.2 s for two minutes, printing ``alive N``; the kill test ends one process and watches the
others end.
"""

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

from canrig_jax.papers import canrig as canrig_paper


def _flat(tree) -> "np.ndarray":  # noqa: F821
    import equinox as eqx
    import jax
    import numpy as np

    leaves = jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    return np.concatenate([np.asarray(leaf, np.float64).ravel() for leaf in leaves])


def run(out: Path, steps: int) -> None:
    import jax
    import numpy as np

    from canrig_jax import autorig, canrig, distributed, inverse, pbs
    from canrig_jax.autorig._data import head_rig, make_head, pose_displacements, quartic_pose_set
    from canrig_jax.data import ict_identity, load_ict, load_livelinkface
    from canrig_jax.mesh import edge_graph
    from canrig_jax.rig import evaluate_batch, ict_linear_rig, ict_quartic_rig, random_sparse_poses

    group = distributed.initialize()
    print(f"{group.describe()}; devices {jax.devices()}", flush=True)
    result, seconds = {}, {}

    rig, _ = ict_quartic_rig(progress=False)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning)
        capture = load_livelinkface().weights_for(rig.names, missing="zero")

    # CANRig: 4 examples per step, data-parallel over every device
    train_capture, _ = canrig_paper.split_capture(capture[:12])
    data = canrig.build_training_set(rig, train_capture, n_random=6, n_pool=40, seed=0)
    examples = canrig.ExampleOptions(batch=4, n_vertices=48, n_handles=(3, 12), handle_bucket=12)
    options = canrig.TrainOptions(steps=steps, log_every=1, examples=examples)
    result["canrig_start"] = _flat(canrig.train(data, options, progress=False, stop_after=0).model)
    t = time.perf_counter()
    trained = canrig.train(data, options, progress=False)
    seconds["canrig"] = time.perf_counter() - t
    result["canrig_params"] = _flat(trained.model)
    result["canrig_losses"] = np.array([h["loss"] for h in trained.history])

    # CANRig-PBS on 40 patches of the ICT face
    face = ict_linear_rig()
    neutral = np.asarray(face.neutral, np.float32)
    layout = pbs.patch_layout(neutral, np.asarray(face.faces), 40, rings=2)
    poses = random_sparse_poses(np.random.default_rng(7), 16, face.names)
    shapes = np.asarray(evaluate_batch(face, poses), np.float32)
    basis, _ = pbs.pbs_basis(neutral, shapes, 6)
    distances = pbs.seed_distances(layout, edge_graph(neutral, np.asarray(face.faces)))
    pool = np.random.default_rng(0).choice(len(neutral), 200, replace=False)
    pbs_data = pbs.build_pbs_training_set(neutral, shapes, layout, basis, distances, pool)
    pbs_options = pbs.PBSTrainOptions(
        width=32, patch_width=16, fourier=2, steps=steps, batch=2, n_handles=(20, 40),
        handle_bucket=20, n_vertices=64, log_every=1,
    )  # fmt: skip
    result["pbs_start"] = _flat(
        pbs.train_pbs(pbs_data, pbs_options, progress=False, stop_after=0)[0]
    )
    t = time.perf_counter()
    model, _, _, history = pbs.train_pbs(pbs_data, pbs_options, progress=False)
    seconds["pbs"] = time.perf_counter() - t
    result["pbs_params"] = _flat(model)
    result["pbs_losses"] = np.array([h["loss"] for h in history])

    # RigAnyFace on one decimated ICT identity, 2 heads per step
    pose_set = quartic_pose_set(rig)
    ict_head = load_ict(parts=None)
    displacements = pose_displacements(head_rig(rig, ict_head), pose_set)
    head = make_head(
        ict_head, displacements, np.random.default_rng(3).standard_normal(100), "decimate_600",
        name="decimate_600",
    )  # fmt: skip
    head_data = autorig.training_set([head], pose_set, k=32, progress=False)
    raf = autorig.RigAnyFaceTrainOptions(
        width=8, global_size=4, global_width=8, k=32, steps=steps, warmup_steps=1,
        poses_per_step=4, heads_per_step=2, log_every=1,
    )  # fmt: skip
    start = autorig.train_riganyface(head_data, pose_set, raf, progress=False, stop_after=0)
    result["riganyface_start"] = _flat(start.model)
    t = time.perf_counter()
    trained = autorig.train_riganyface(head_data, pose_set, raf, progress=False)
    seconds["riganyface"] = time.perf_counter() - t
    result["riganyface_params"] = _flat(trained.model)
    result["riganyface_losses"] = np.array([h["loss"] for h in trained.history])

    # the inverse rig of 45 capture frames (odd: the last share is padded)
    problem = inverse.prepare(rig)
    targets = np.asarray(evaluate_batch(rig, capture[:45]))
    method = inverse.QuarticNewton(alpha=0.1)
    t = time.perf_counter()
    solution = inverse.solve_sequence(problem, targets, method, across_processes=True)
    jax.block_until_ready(solution.weights)
    seconds["inverse"] = time.perf_counter() - t
    result["inverse_weights"] = np.asarray(solution.weights)
    result["inverse_objective"] = np.asarray(solution.objective)
    result["inverse_converged"] = np.asarray(solution.stats["converged"])
    result["inverse_truth"] = np.asarray(capture[:45])
    # the same take as one batch (one process, no sharing): float32 rounds with batch size
    result["inverse_one_batch"] = np.asarray(
        inverse.solve_sequence(problem, targets, method).weights
    )

    # the auto-rig of two heads (two ICT identities' neutrals, cm)
    identities = np.random.default_rng(11).standard_normal((2, 100))
    heads = [(ict_identity(c, model=ict_head), np.asarray(ict_head.faces)) for c in identities]
    t = time.perf_counter()
    rigs = autorig.auto_rig_heads(heads, method=autorig.RigAnyFaceNetwork(), across_processes=True)
    seconds["autorig"] = time.perf_counter() - t
    for i, r in enumerate(rigs):
        result[f"autorig_{i}_deltas"] = np.asarray(r.rig.deltas)
    result["autorig_names"] = np.array(rigs[0].rig.names)

    if group.is_main:
        out.mkdir(parents=True, exist_ok=True)
        np.savez(out / "result.npz", **result)
        info = {"processes": group.processes, "devices": jax.device_count(), "seconds": seconds}
        (out / "timing.json").write_text(json.dumps(info, indent=1))
    print(f"process {group.process_id}: done {json.dumps(seconds)}", flush=True)


def wait() -> None:
    import jax.numpy as jnp
    import numpy as np
    from jax.experimental import multihost_utils

    from canrig_jax import distributed

    group = distributed.initialize()
    print(group.describe(), flush=True)
    for i in range(600):
        total = multihost_utils.process_allgather(jnp.float32(i))
        print(f"alive {i} {float(np.sum(total))}", flush=True)
        time.sleep(0.2)
    print(f"process {group.process_id}: no one died", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("run", "wait"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--steps", type=int, default=3)
    args = parser.parse_args(argv)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    if args.mode == "wait":
        wait()
    else:
        if args.out is None:
            parser.error("run: --out is required")
        run(args.out, args.steps)
    return 0


if __name__ == "__main__":
    sys.exit(main())
