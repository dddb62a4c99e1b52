"""Patch blendshapes on the whole ICT head: the patch layout, the basis, how well PBS
represents held-out shapes, Table 5 (global blendshapes, the local fit alone and the networks
trained by ``canrig_pbs_train.py``), Figure 8, Table 6 and the forward pass's timing.

    python experiments/canrig_pbs.py --out experiments/results/canrig_pbs

Whole-head shapes: the linear ICT rig on all 26,719 vertices (its 53 expressions; the
ict-quartic correctives exist on the face part only) at the Live Link capture's first half and
400 random sparse poses (training: the basis is picked from them), held out: the capture's
second half and 100 random sparse poses of another seed (``canrig.held_out_poses``). The
trained rows read OUT/models/NAME/checkpoint.eqx (a missing one is skipped). Writes
results.json, table.md, COMMAND, patch_layout.png, pbs_error.png (and whole_head_edit.png,
table6_error.png with trained models). The protocols are ``canrig_jax.papers.canrig.whole_head``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from canrig_jax._io import save_json, save_text  # noqa: E402
from canrig_jax._metrics import CM_TO_MM  # noqa: E402
from canrig_jax._provenance import experiment_command, provenance  # noqa: E402
from canrig_jax._timing import median_ms  # noqa: E402
from canrig_jax.canrig import ShapePreservingCANRig, influence_mask
from canrig_jax.mesh import weighted_geodesic_distance
from canrig_jax.papers.canrig.whole_head import (  # noqa: E402
    EVAL_FALLOFF_PER_CM,
    EVAL_RADIUS_CM,
    FIGURE8_MODELS,
    FIGURE8_TAG,
    LOCAL_FIT_RIDGE,
    MODELS_DIR,
    TABLE5_MODELS,
    add_whole_head_options,
    dialogue_clips,
    handle_reach,
    pbs_markdown,
    pbs_protocol,
    pbs_representation,
    pbs_training_set,
    table5_baselines,
    table5_handles,
    table5_local_fit,
    table5_reconstruct,
    table5_trained_row,
    table6,
    whole_head,
    whole_head_options_from_args,
)
from canrig_jax.pbs import PBSTrainOptions, load_pbs_model, pbs_shape
from canrig_jax.render import plot_vertex_scalar, save_figure  # noqa: E402
from canrig_jax.watchdog import run_watched  # noqa: E402


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, default=None)
    parser.add_argument("--no-progress", action="store_true", help="print no progress lines")
    return add_whole_head_options(parser)


def _trained_rows(head, data, handles, handle_distance, models):
    """Table 5's trained rows, their networks and one whole-head forward pass each at 200
    handles (ms; patch queries cached once per mesh, as the per-vertex reference's), and
    Figure 8's rows."""
    trained, nets, forward, figure8 = {}, {}, {}, {}
    h200, d200 = jnp.asarray(handles[:200]), jnp.asarray(handle_distance[:, :200])
    test = jnp.asarray(head.test_shapes[:1])
    for name in (*TABLE5_MODELS, *(v + FIGURE8_TAG for v in FIGURE8_MODELS)):
        checkpoint = models / name / "checkpoint.eqx"
        if not checkpoint.exists():
            print(f"{name}: no checkpoint at {checkpoint}, row skipped")
            continue
        net, row = table5_trained_row(head, data, checkpoint, handles, handle_distance)
        print(f"{name}: {row}")
        if name.endswith(FIGURE8_TAG):
            figure8[name.removesuffix(FIGURE8_TAG)] = row
            continue
        trained[name], nets[name] = row, net
        queries = net.encode_patches(data.seeds)
        forward[name] = median_ms(
            lambda net=net, q=queries: table5_reconstruct(net, data, h200, d200, test, q)
        )
    return trained, nets, forward, figure8


def _layout_timing(head, weights) -> dict:
    """One shape through W_layout: the gather form against a scipy.sparse product (ms)."""
    layout, neutral, basis = head.layout, head.neutral, head.basis
    w_layout = layout.matrix()
    weights_j, basis_j, neutral_j = jnp.asarray(weights), jnp.asarray(basis), jnp.asarray(neutral)

    def sparse():
        per_vertex = w_layout @ np.asarray(weights_j)  # (N, B)
        return neutral + np.einsum("nb,bnk->nk", per_vertex, basis)

    return {
        "pbs_shape_gather_ms": median_ms(lambda: pbs_shape(layout, neutral_j, basis_j, weights_j)),
        "pbs_shape_scipy_sparse_ms": median_ms(sparse),
    }


def _dense_reference_ms(head, handles):
    """One dense per-vertex forward pass (an untrained ShapePreservingCANRig, the encoder
    sizes of PBSTrainOptions) on all vertices at these handles: the timing reference."""
    o = PBSTrainOptions()
    neutral = head.neutral
    net = ShapePreservingCANRig(
        neutral,
        n_heads=o.n_heads,
        latent=o.latent,
        width=o.width,
        n_layers=o.n_layers,
        fourier=o.fourier,
        key=jax.random.PRNGKey(0),
    )
    # (H, V): paths from every vertex to the handles (the transpose of a bridged graph)
    distance = weighted_geodesic_distance(head.graph.T.tocsr(), handles)
    mask = influence_mask(distance.T, EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM)
    queries = net.encode_queries(jnp.asarray(neutral))
    base = jnp.asarray(neutral)
    d = jnp.asarray(head.test_shapes[0][handles] - neutral[handles])
    index = jnp.asarray(handles)
    call = eqx.filter_jit(lambda net, q, base, m, d: net(q, base, base[index], base[index], d, m))
    return median_ms(lambda: call(net, queries, base, mask, d))


def main(argv=None):
    args = _parser().parse_args(argv)
    options = whole_head_options_from_args(args)
    command = experiment_command(__file__, argv)
    say = (lambda *_: None) if args.no_progress else print
    head = whole_head(options, args.data_dir, progress=say)
    pbs, error, fitted = pbs_representation(head)
    handles = table5_handles(head)
    table5 = table5_baselines(head, handles)
    data, distances = pbs_training_set(head)
    handle_distance = distances[:, handles]
    reach = handle_reach(head, handle_distance)
    models = args.out / MODELS_DIR
    trained, nets, forward, figure8 = _trained_rows(head, data, handles, handle_distance, models)
    # the local fit alone (no network): CANRig-PBS's local prior at its trained ridge, or at
    # the default initial one when the per_patch model has no prior
    prior = nets.get("per_patch")
    local_prior = prior is not None and prior.local_prior
    ridge = float(jnp.exp(prior.log_ridge)) if local_prior else LOCAL_FIT_RIDGE
    table5["local_fit"] = table5_local_fit(head, handles, handle_distance, ridge)
    table5.update(trained)
    timing = _layout_timing(head, fitted[0])
    print(
        f"PBS fit: mean {pbs['fit_mean_mm']:.4f} mm, p95 {pbs['fit_p95_mm']:.4f} mm; gather "
        f"{timing['pbs_shape_gather_ms']:.2f} ms, "
        f"scipy.sparse {timing['pbs_shape_scipy_sparse_ms']:.2f} ms"
    )
    forward["dense_per_vertex_reference"] = _dense_reference_ms(head, handles[:200])
    dialogue, run = {}, None
    if trained:
        clips = dialogue_clips(head, 6 if args.quick else 45)
        dialogue, run = table6(head, data, distances, models, clips, progress=say)
    results = {
        "pbs": pbs,
        "table5": table5,
        "figure8": figure8,
        # the schema: table6 -> method -> {rig_inversion_mm, mouth_difference_mm,
        # rest_of_face_change_mm}; the handles, reach floor, frames and protocol beside it
        "table6": dialogue.get("methods", {}),
        "table6_setup": {k: v for k, v in dialogue.items() if k != "methods"},
        "table5_reach": reach,
        "forward_ms_whole_head": forward.get("per_patch"),
        "forward_ms": forward,
        "timing": timing,
        "protocol": pbs_protocol(options, head),
        "provenance": provenance(command),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_json(args.out / "results.json", results)
    text = pbs_markdown(results, options, command, len(head.basis), len(head.test))
    save_text(args.out / "table.md", text)
    _command_file(args.out, [*trained, *(k + FIGURE8_TAG for k in figure8)], figure8, command)
    if "per_patch" in trained:
        path = args.out / "whole_head_edit.png"
        _figure_edit(head, data, distances, handles[:200], models / "per_patch", path)
    if run is not None:
        _figure_dialogue(head, run, args.out / "table6_error.png")
    _figure_layout(head, options.patches, args.out / "patch_layout.png")
    fig, ax = plt.subplots(figsize=(5, 5))
    title = "PBS fit, mean held-out error (0-0.2 mm)"
    plot_vertex_scalar(
        ax, head.neutral, head.faces, error.mean(axis=0), vmin=0, vmax=0.2, title=title
    )
    save_figure(fig, args.out / "pbs_error.png")
    print(text)


def _command_file(out, trained, figure8, command):
    """OUT/COMMAND: each trained model's command (from its train.json), then this one."""
    commands = [
        json.loads((out / MODELS_DIR / name / "train.json").read_text())["provenance"]["command"]
        for name in trained
        if (out / MODELS_DIR / name / "train.json").exists()
    ]
    save_text(
        out / "COMMAND",
        "# training, one model each (resumable; the same command continues a run)\n"
        + "".join(c + "\n" for c in commands)
        + (
            "# (per_patch_fig8 is the per_patch run's checkpoint at step 1,000, copied while it\n"
            "# trained; its command reproduces it bit-identically. Its 21 MB checkpoint is not\n"
            "# committed: run that command before the evaluation to regenerate Figure 8's row.)\n"
            if "per_patch" in figure8
            else ""
        )
        + "# evaluation (Table 5, Figure 8, Table 6, timing, figures)\n"
        + command
        + "\n",
    )


def _figure_layout(head, n_patches, path):
    """The patches in shuffled colours, front and side."""
    cell = np.asarray(head.layout.cell).astype(float)
    shuffled = np.random.default_rng(0).permutation(n_patches)
    colour = np.where(cell >= 0, shuffled[np.maximum(cell, 0).astype(int)], 0)
    fig, axes = plt.subplots(1, 2, figsize=(9, 5))
    for ax, view in zip(axes, ("front", "side"), strict=True):
        plot_vertex_scalar(
            ax,
            head.neutral,
            head.faces,
            colour,
            vmin=0,
            vmax=n_patches,
            cmap="tab20",
            view=view,
            title=f"{n_patches} patches ({view})",
        )
    save_figure(fig, path)


def _figure_edit(head, data, distances, handles, folder, path):
    """The per-patch model at 200 handles on the held-out shape that moves most."""
    neutral, faces, test = head.neutral, head.faces, head.test_shapes
    pick = int(np.argmax(np.linalg.norm(test - neutral, axis=-1).mean(axis=1)))
    shape = data.weights.shape
    net, _ = load_pbs_model(folder / "checkpoint.eqx", neutral, shape[1], shape[2])
    out = np.asarray(
        table5_reconstruct(net, data, handles, distances[:, handles], test[pick : pick + 1])[0]
    )
    fig, axes = plt.subplots(1, 3, figsize=(13, 5))
    panels = (
        (test[pick], np.linalg.norm(test[pick] - neutral, axis=-1) * CM_TO_MM, 10, "target motion"),
        (out, np.linalg.norm(out - neutral, axis=-1) * CM_TO_MM, 10, "CANRig-PBS motion"),
        (out, np.linalg.norm(out - test[pick], axis=-1) * CM_TO_MM, 3, "error"),
    )
    for ax, (mesh, value, top, title) in zip(axes, panels, strict=True):
        plot_vertex_scalar(ax, mesh, faces, value, vmin=0, vmax=top, title=f"{title} (0-{top} mm)")
    axes[0].scatter(*neutral[handles][:, :2].T, s=2, c="k")
    fig.suptitle(f"200 handles, whole head (26,719 vertices), held-out shape {pick}")
    save_figure(fig, path)


def _figure_dialogue(head, run, path):
    """Figure 12 analog: per method, the distance to the target frame in the middle of the
    clip (mm) and the mouth region."""
    frame = len(run["source"]) // 2
    names = list(run["outputs"])
    fig, axes = plt.subplots(1, len(names) + 1, figsize=(4 * (len(names) + 1), 4.5))
    region = run["region"].astype(float)
    source = run["source"][frame]
    plot_vertex_scalar(axes[0], source, head.faces, region, vmin=0, vmax=1, title="mouth region")
    for ax, name in zip(axes[1:], names, strict=True):
        edited = run["outputs"][name][frame]
        distance = np.linalg.norm(edited - run["target"][frame], axis=-1) * CM_TO_MM
        title = f"{name} (0-5 mm)"
        plot_vertex_scalar(ax, edited, head.faces, distance, vmin=0, vmax=5, title=title)
    save_figure(fig, path)


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)
