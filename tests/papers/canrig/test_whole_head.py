"""The evaluation protocols of patch blendshapes on the whole ICT head
(``papers.canrig.whole_head``) on
a small setup of the real head (40 patches, a few poses): the options' command line, exact
representation of basis shapes, Table 5's rows against their limits (no motion, an infinite
ridge), the handles' reach and the mouth handles' isolation, Table 6's floor, and the
committed tables and protocol rendered back from their results."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from canrig_jax._checkpoint import parameter_count
from canrig_jax.canrig import CLAMP, influence_mask, influence_reach
from canrig_jax.data import load_ict
from canrig_jax.mesh import edge_graph
from canrig_jax.papers.canrig.whole_head import (
    DIALOGUE_REACH_CM,
    EVAL_FALLOFF_PER_CM,
    EVAL_RADIUS_CM,
    MODELS_DIR,
    POOL_SIZE,
    REGIONS,
    SWEEP_HEADER,
    WholeHead,
    WholeHeadOptions,
    add_whole_head_options,
    check_model_matches,
    dialogue_clips,
    handle_reach,
    mask_graph,
    mouth_handles,
    pbs_markdown,
    pbs_protocol,
    pbs_representation,
    pbs_training_set,
    region_errors,
    sweep_markdown,
    table5_baselines,
    table5_handles,
    table5_local_fit,
    table5_reconstruct,
    table5_trained_row,
    table6,
    table6_sweep,
    whole_head,
    whole_head_options_from_args,
)
from canrig_jax.pbs import PBSTrainOptions, patch_layout, pbs_basis, seed_distances, train_pbs
from canrig_jax.rig import evaluate_batch, ict_linear_rig, random_sparse_poses

RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results"
QUIET = dict(progress=lambda *_: None)


@pytest.fixture(scope="module")
def head(data_dir, livelink_weights):
    """The whole ICT head (the linear rig on every vertex) with 40 patches, a 6-offset basis
    from 12 random poses, held out: two of the basis shapes (PBS and GBS represent them) and
    four other poses; the capture is the real Live Link one."""
    options = WholeHeadOptions(patches=40, basis=7, handles=60, n_random=12)
    model = load_ict(data_dir, parts=None)
    rig = ict_linear_rig(data_dir, parts=None)
    neutral, faces = np.asarray(rig.neutral, np.float32), np.asarray(rig.faces)
    active = np.linalg.norm(np.asarray(rig.deltas), axis=-1).max(axis=0) > 0
    layout = patch_layout(neutral, faces, options.patches, rings=2, active=active)
    poses = random_sparse_poses(np.random.default_rng(7), 16, rig.names)
    shapes = np.asarray(evaluate_batch(rig, poses), np.float32)
    basis, picked = pbs_basis(neutral, shapes[:12], options.basis)
    skin = model.part_mask(("Face", "Head and Neck"))
    return WholeHead(
        options=options,
        model=model,
        rig=rig,
        neutral=neutral,
        faces=faces,
        active=active,
        parts=["Face"],
        layout=layout,
        layout_seconds=0.0,
        capture=livelink_weights,
        capture_train=livelink_weights[:90],
        train=poses[:12],
        test=poses[[*picked[:2], 12, 13, 14, 15]],
        train_shapes=shapes[:12],
        test_shapes=np.concatenate([shapes[picked[:2]], shapes[12:]]),
        basis=basis,
        picked=picked,
        skin=skin,
        handle_region=skin,
        graph=mask_graph(options, model),
    )


@pytest.fixture(scope="module")
def training(head):
    return pbs_training_set(head)


def test_the_options_come_from_the_command_line():
    parser = add_whole_head_options(argparse.ArgumentParser())
    assert whole_head_options_from_args(parser.parse_args([])) == WholeHeadOptions()
    args = parser.parse_args(["--graph", "attached", "--attach", "Teeth", "--quick"])
    options = whole_head_options_from_args(args)
    assert options.attach == ("Teeth",) and options.graph == "attached"
    assert (options.patches, options.n_random) == (60, 60)  # --quick
    with pytest.raises(SystemExit):
        parser.parse_args(["--handles-on", "teeth"])
    with pytest.raises(ValueError, match="graph"):
        WholeHeadOptions(graph="geodesic")
    with pytest.raises(ValueError, match="handles_on"):
        WholeHeadOptions(handles_on="teeth")
    with pytest.raises(ValueError, match="patches"):
        WholeHeadOptions(patches=0)


def test_mask_graphs_add_edges_to_the_mesh_one(head):
    mesh = mask_graph(WholeHeadOptions(graph="mesh"), head.model)
    assert (mesh != edge_graph(head.neutral, head.faces)).nnz == 0
    bridged = head.graph  # bridged: the mesh's edges and the floating parts' exits
    assert bridged.nnz > mesh.nnz
    attached = mask_graph(WholeHeadOptions(graph="attached", attach=("Teeth",)), head.model)
    assert attached.nnz > bridged.nnz


def test_check_model_matches_refuses_another_graph(head, tmp_path):
    (tmp_path / "train.json").write_text(json.dumps({"graph": "mesh", "handles_on": "skin"}))
    check_model_matches(WholeHeadOptions(graph="mesh"), tmp_path)
    with pytest.raises(ValueError, match="--graph: "):
        check_model_matches(head.options, tmp_path)


def test_region_errors_split_the_whole_head_mean(head):
    n = len(head.neutral)
    error = np.zeros((3, n))
    face = slice(*head.model.part_vertex_range[0])  # the face is the head's first part
    error[:, face] = 2.0
    regions = region_errors(head.model, error)
    assert list(regions) == list(REGIONS)
    assert regions["face"]["mean_mm"] == 2.0 and regions["head_and_neck"]["mean_mm"] == 0.0
    assert regions["face"]["share_of_mean_mm"] == pytest.approx(error.mean())
    error = np.random.default_rng(0).uniform(size=(3, n)) * head.active  # eyeballs still
    shares = sum(r["share_of_mean_mm"] for r in region_errors(head.model, error).values())
    assert shares == pytest.approx(error.mean())  # the regions cover every moving vertex


def test_pbs_represents_its_basis_shapes_exactly(head):
    summary, error, fitted = pbs_representation(head)
    assert error.shape == (6, len(head.neutral)) and fitted.shape[:2] == (6, 40)
    assert error[:2].max() < 0.01  # mm: the first two held-out shapes are basis shapes
    assert error[2:].mean() > 10 * error[:2].mean()
    sizes = summary["patch_size"]
    assert sizes["min"] <= sizes["median"] <= sizes["max"]
    assert summary["active_vertices"] == int(head.active.sum())
    assert summary["fit_mean_mm"] == pytest.approx(error.mean())


def test_table5_handles_spread_over_the_skin(head):
    handles = table5_handles(head)
    assert len(handles) == len(np.unique(handles)) == 60 and head.skin[handles].all()


def test_table5_baselines_against_no_motion(head):
    handles = table5_handles(head)
    table5 = table5_baselines(head, handles)
    offsets = np.linalg.norm(head.test_shapes - head.neutral, axis=-1) * 10.0
    assert table5["no_motion"]["mean_mm"] == pytest.approx(offsets.mean(axis=1).mean(), rel=1e-5)
    # the linear rig's poses lie in the span of its 53 expressions: GBS nearly recovers them
    assert table5["gbs_ict_53"]["mean_mm"] < 0.2 * table5["no_motion"]["mean_mm"]
    assert table5["gbs_pbs_basis"]["basis_size"] == len(head.basis)
    assert table5["gbs_pbs_basis"]["mean_mm"] < table5["no_motion"]["mean_mm"]
    assert set(table5["gbs_ict_53"]["regions"]) == set(REGIONS)


def test_the_local_fit_row_tends_to_no_motion_as_the_ridge_grows(head, training):
    _, distances = training
    handles = table5_handles(head)
    no_motion = (np.linalg.norm(head.test_shapes - head.neutral, axis=-1) * 10.0).mean()
    stiff = table5_local_fit(head, handles, distances[:, handles], 1e9)
    assert stiff["mean_mm"] == pytest.approx(no_motion, rel=1e-4) and stiff["ridge"] == 1e9
    assert table5_local_fit(head, handles, distances[:, handles], 1e-2)["mean_mm"] < no_motion


def test_handle_reach_counts_patches_by_region(head, training):
    _, distances = training
    reach = handle_reach(head, distances[:, table5_handles(head)])
    assert reach["reach_cm"] == pytest.approx(
        float(influence_reach(EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP))
    )
    # the reach is where the clamped mask becomes exactly zero
    at = np.array([[reach["reach_cm"] * 0.95, reach["reach_cm"] * 1.001]], np.float32)
    mask = np.asarray(influence_mask(at, EVAL_RADIUS_CM, EVAL_FALLOFF_PER_CM, CLAMP))
    assert mask[0, 0] > 0 and mask[0, 1] == 0
    face = reach["regions"]["face"]
    assert face["patches"] > 0 and 0 <= face["within_radius"] <= face["within_reach"] <= 1
    everywhere = handle_reach(head, np.zeros((40, 3)))["regions"]
    assert all(r["within_radius"] == 1.0 for r in everywhere.values() if r["patches"])
    assert sum(r["patches"] for r in everywhere.values()) <= 40


def test_the_training_set_draws_its_pool_from_the_handle_region(head, training):
    data, distances = training
    pool = np.asarray(data.pool)
    assert len(pool) == len(np.unique(pool)) == min(POOL_SIZE, int(head.skin.sum()))
    assert head.skin[pool].all()
    assert distances.shape == (40, len(head.neutral))
    np.testing.assert_array_equal(distances[np.arange(40), np.asarray(head.layout.seeds)], 0)


def test_mouth_handles_move_no_patch_outside_the_mouth(head, training):
    _, distances = training
    clips = dialogue_clips(head, 3)
    np.testing.assert_allclose(
        clips.source, np.asarray(evaluate_batch(head.rig, head.capture[90:93])), atol=1e-6
    )
    np.testing.assert_array_equal(clips.region, head.layout.covered_by(clips.mouth_patch))
    index = mouth_handles(head.neutral, distances, clips.mouth, clips.mouth_patch, 8)
    assert clips.mouth[index].all() and len(np.unique(index)) == 8
    assert distances[~clips.mouth_patch][:, index].min() > DIALOGUE_REACH_CM
    with pytest.raises(ValueError, match="count"):
        mouth_handles(head.neutral, distances, clips.mouth, clips.mouth_patch, 10**6)


def test_table6_without_networks_holds_gbs_and_a_floor_below_no_edit(head, training, tmp_path):
    data, distances = training
    clips = dialogue_clips(head, 3)
    table, run = table6(head, data, distances, tmp_path, clips, n_mouth=8, **QUIET)
    assert set(table["methods"]) == {"gbs_19", "gbs_ict_53"}  # no checkpoint in tmp_path
    assert table["mouth_handles"] == 8 and table["frames"]["source"] == [90, 92]
    assert 0 <= table["reach_floor_mm"] <= table["no_edit_mouth_difference_mm"]
    # ICT's 53 expressions span the linear rig's frames: the mouth takes the target's
    gbs = table["methods"]["gbs_ict_53"]
    assert gbs["mouth_difference_mm"] < 0.5 * table["no_edit_mouth_difference_mm"]
    assert run["outputs"]["gbs_19"].shape == clips.source.shape


def test_the_sweep_floor_never_rises_with_more_mouth_handles(head, training, tmp_path):
    """Farthest-point handles: the 6 include the 2, so they reach every patch the 2 do."""
    data, distances = training
    clips = dialogue_clips(head, 2)
    sweep = table6_sweep(head, data, distances, tmp_path, clips, [2, 6], **QUIET)
    assert sweep["2"]["reach_floor_mm"] >= sweep["6"]["reach_floor_mm"]
    assert sweep["2"]["unreached_region_vertices"] >= sweep["6"]["unreached_region_vertices"]
    assert sweep["2"]["per_patch_rest_of_face_change_max_mm"] is None  # no network here
    with pytest.raises(ValueError, match="counts"):
        table6_sweep(head, data, distances, tmp_path, clips, [0], **QUIET)


@pytest.mark.parametrize(
    "folder, options",
    [
        ("canrig_pbs_attached_local_prior", WholeHeadOptions(graph="attached")),
        ("canrig_pbs_local_prior_moving", WholeHeadOptions(handles_on="moving")),
    ],
)
def test_the_committed_protocols_render_back(folder, options, head):
    results = json.loads((RESULTS / folder / "results.json").read_text())
    assert pbs_protocol(options, head) == results["protocol"]  # 180 capture frames, as here


def test_the_committed_tables_render_back():
    folder = RESULTS / "canrig_pbs_attached_local_prior"  # the standard configuration
    results = json.loads((folder / "results.json").read_text())
    command = results["provenance"]["command"]
    text = pbs_markdown(results, WholeHeadOptions(graph="attached"), command, 18, 190)
    before, sweep = (folder / "table.md").read_text().split(SWEEP_HEADER)
    # (the title no longer names the issue)
    assert text.splitlines()[1:] == before.rstrip("\n").splitlines()[1:]
    section = sweep_markdown(
        results["table6_handle_sweep"]["mouth_difference_mm"],
        results["table6_handle_sweep"]["provenance"]["command"],
    )
    assert section == (SWEEP_HEADER + sweep).rstrip("\n")
    del results["figure8"]["per_patch"], results["figure8"]["base_multiplied"]
    del results["figure8"]["no_modulation"]
    text = pbs_markdown(results, WholeHeadOptions(graph="attached"), command, 18, 190)
    assert "Figure 8: no variant trained in this folder (`canrig_pbs_train.py" in text


@pytest.mark.slow
def test_whole_head_quick(data_dir):
    head = whole_head(WholeHeadOptions().quick(), data_dir, progress=print)
    assert head.layout.n_patches == 60 and len(head.basis) == 18
    assert len(head.train_shapes) == len(head.capture_train) + 60
    assert len(head.test_shapes) == len(head.capture) - len(head.capture_train) + 100
    assert head.handle_region is head.skin
    np.testing.assert_array_equal(head.basis, head.train_shapes[head.picked] - head.neutral)
    assert seed_distances(head.layout, head.graph).shape == (60, len(head.neutral))


@pytest.mark.slow
def test_a_trained_network_keeps_its_exact_zeros_in_table5_and_table6(head, training, tmp_path):
    """A CANRig-PBS network (two training steps) through Table 5's row and Table 6: zero
    displacements give the base frame exactly, and nothing moves outside the mouth region."""
    data, distances = training
    folder = tmp_path / MODELS_DIR / "per_patch"
    options = PBSTrainOptions(steps=2, n_handles=(20, 40), handle_bucket=20, n_vertices=256)
    net, *_ = train_pbs(data, options, checkpoint=folder / "checkpoint.eqx", progress=False)
    handles = table5_handles(head)
    trained, row = table5_trained_row(
        head, data, folder / "checkpoint.eqx", handles, distances[:, handles]
    )
    assert row["steps"] == 2 and row["parameters"] == parameter_count(net)
    shapes = np.asarray(
        table5_reconstruct(trained, data, handles, distances[:, handles], head.test_shapes)
    )
    error = np.linalg.norm(shapes - head.test_shapes, axis=-1).mean(axis=1) * 10.0
    assert row["mean_mm"] == pytest.approx(error.mean(), rel=1e-6)
    clips = dialogue_clips(head, 2)
    table, run = table6(head, data, distances, tmp_path / MODELS_DIR, clips, 8, **QUIET)
    assert table["methods"]["per_patch"]["rig_inversion_mm"] == 0.0
    assert table["methods"]["per_patch"]["rest_of_face_change_mm"] == 0.0
    assert table["methods"]["per_patch"]["mouth_difference_mm"] >= table["reach_floor_mm"] - 1e-6
