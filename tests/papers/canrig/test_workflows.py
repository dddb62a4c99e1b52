"""The evaluation protocols of the CANRig workflows experiment (``papers.canrig.workflows``):
Table 4's random protocol and cells against independent computations, the floor against the
masks' exact zeros, the workflows' guarantees as the protocols report them (on the rig with no
network: cheap to compile), and the committed tables rendered back from their results."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canrig_jax.canrig import (
    CLAMP,
    FitOptions,
    NeuralRig,
    expression_region,
    influence_mask,
    pose_a_to_b,
)
from canrig_jax.canrig._data import RADII_CM
from canrig_jax.papers.canrig.workflows import (
    DIALOGUE_HANDLES,
    DIALOGUE_RADIUS_CM,
    FALLOFF_PER_CM,
    HANDLE_COUNTS,
    LAYER_SCHEDULE,
    a_to_b_cell,
    a_to_b_table,
    clip_edit_protocol,
    dialogue_handle_vertices,
    dialogue_table,
    layers_protocol,
    local_fit_from_selection,
    network_rig,
    random_pairs,
    results_of_the_same_pairs,
    select_local_fit,
    table4_protocol,
    unreached_floor,
    workflow_data,
    workflows_markdown,
)
from canrig_jax.pbs import local_fit_rig, patch_layout, pbs_basis
from canrig_jax.rig import evaluate_batch, random_sparse_poses

RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results"
OPTIONS = FitOptions(max_steps=4, lsmr_steps=8)


@pytest.fixture(scope="module")
def setup(ict_face):
    """A ``LocalFitRig`` on the ICT face (the workflows run on any rig; this one compiles in
    seconds) and eight real expressions (S, V, 3)."""
    neutral, faces = np.asarray(ict_face.neutral, np.float32), np.asarray(ict_face.faces)
    poses = random_sparse_poses(np.random.default_rng(5), 30, ict_face.names)
    shapes = np.asarray(evaluate_batch(ict_face, poses), np.float32)
    basis, _ = pbs_basis(neutral, shapes[8:], 8)
    layout = patch_layout(neutral, faces, 60, rings=2)
    return NeuralRig(local_fit_rig(layout, basis, ridge=1e-3), neutral, faces), shapes[:8]


def test_random_pairs_never_pair_a_pose_with_itself():
    pairs = random_pairs(5, 2000, np.random.default_rng(0))
    assert pairs.shape == (2000, 2)
    assert np.all(pairs[:, 0] != pairs[:, 1])
    assert pairs.min() == 0 and pairs.max() == 4  # every pose drawn on both sides
    assert set(np.unique(pairs[:, 1])) == set(range(5))
    with pytest.raises(ValueError, match="n_poses"):
        random_pairs(1, 3, np.random.default_rng(0))


def test_table4_protocol_draws_one_distinct_handle_set_per_pair_and_count():
    pairs, sets, rng = table4_protocol(30, 500, 7, seed=3)
    np.testing.assert_array_equal(pairs, random_pairs(30, 7, np.random.default_rng(3)))
    assert list(sets) == list(HANDLE_COUNTS)
    for n, drawn in sets.items():
        assert len(drawn) == 7
        assert all(len(np.unique(h)) == n and h.max() < 500 for h in drawn)
    # the generator continues from the sets: the layers' handles are not the sets again
    again = np.random.default_rng([3, 1])
    for n in HANDLE_COUNTS:
        for h in sets[n]:
            np.testing.assert_array_equal(h, again.choice(500, n, replace=False))
    assert rng.integers(1 << 30) == again.integers(1 << 30)


def test_a_to_b_cell_summarises_the_pairs():
    rng = np.random.default_rng(1)
    direct = rng.uniform(1, 2, 10)
    fitted = direct[:4] - 0.5
    vertices = [rng.uniform(0, 3, 50) for _ in range(4)]
    cell = a_to_b_cell(direct, fitted, vertices, direct[:4])
    assert cell["direct_mm"] == pytest.approx(direct.mean())
    assert cell["direct_on_fitted_pairs_mm"] == pytest.approx(direct[:4].mean())
    assert cell["fitted_mm"] == pytest.approx(fitted.mean())
    pooled = np.sort(np.concatenate(vertices))  # 200 values: p95 lies 5% past the 190th
    assert cell["fitted_p95_mm"] == pytest.approx(pooled[189] + 0.05 * (pooled[190] - pooled[189]))
    assert cell["fitted_never_worse"] and cell["fitted_excess_over_direct_pass_max_mm"] == 0.0
    assert (cell["pairs_direct"], cell["pairs_fitted"]) == (10, 4)
    worse = fitted.copy()
    worse[2] = direct[2] + 0.25
    cell = a_to_b_cell(direct, worse, vertices, direct[:4])
    assert not cell["fitted_never_worse"]
    assert cell["fitted_excess_over_direct_pass_max_mm"] == pytest.approx(0.25)
    with pytest.raises(ValueError, match="fitted"):
        a_to_b_cell(direct, [], [], [])


def test_unreached_floor_counts_only_vertices_every_clamped_mask_leaves_still(setup):
    """Independently, from the masks: a vertex beyond the reach has every handle's clamped
    mask exactly 0, so the floor (error there, averaged over all vertices) is at most the
    error of the vertices whose masks are all 0, and close to it; wider radii leave fewer."""
    rig, shapes = setup
    pairs = np.array([[0, 1], [2, 3]])
    sets = {20: [np.arange(0, 9000, 450), np.arange(7, 9000, 450)]}
    floor = unreached_floor(rig, shapes, pairs, sets, progress=lambda _: None)["20"]
    for name, radius in RADII_CM.items():
        floors, unreached = [], []
        for (a, b), index in zip(pairs, sets[20], strict=True):
            mask = influence_mask(rig.handles(index).distance, radius, FALLOFF_PER_CM, CLAMP)
            still = np.asarray(mask).max(axis=1) == 0
            error = np.linalg.norm(shapes[a] - shapes[b], axis=-1) * 10.0
            floors.append(np.where(still, error, 0.0).mean())
            unreached.append(100 * still.mean())
        assert floor[name]["floor_mm"] <= np.mean(floors) + 1e-9
        assert floor[name]["floor_mm"] == pytest.approx(np.mean(floors), rel=0.01)
        assert floor[name]["unreached_percent"] <= np.mean(unreached)
    values = [floor[name]["unreached_percent"] for name in RADII_CM]  # small to large
    assert values == sorted(values, reverse=True) and values[0] > values[-1] > 0


def test_dialogue_handles_keep_their_masks_inside_the_mouth(setup, ict_face):
    rig, _ = setup
    mouth = expression_region(ict_face, threshold=0.3)
    index = dialogue_handle_vertices(rig, mouth)
    assert len(index) == DIALOGUE_HANDLES == len(np.unique(index)) and mouth[index].all()
    mask = influence_mask(rig.handles(index).distance, DIALOGUE_RADIUS_CM, FALLOFF_PER_CM, CLAMP)
    assert np.asarray(mask)[~mouth].max() == 0


# the workflows themselves compile a fit per handle count (tens of seconds each): -m slow


@pytest.mark.slow
def test_a_to_b_table_fits_the_first_pairs_and_never_does_worse(setup):
    rig, shapes = setup
    pairs = np.array([[0, 1], [2, 3], [4, 5]])
    index = np.random.default_rng(2).choice(rig.n_vertices, 200, replace=False)
    handles = rig.handles(index, limit=5.0)
    radii = {"small": 1.0, "medium": 2.0}
    table = a_to_b_table(
        rig,
        shapes,
        pairs,
        lambda p, n: handles,
        1,
        OPTIONS,
        progress=lambda _: None,
        n_fit_main=2,  # the target cell (200 handles, medium) fits more pairs
        handle_counts=(200,),
        radii_cm=radii,
    )
    cells = table["200"]
    assert (cells["small"]["pairs_fitted"], cells["medium"]["pairs_fitted"]) == (1, 2)
    for name, radius in radii.items():
        direct = [
            float(pose_a_to_b(rig, handles, shapes[a], shapes[b], radius, FALLOFF_PER_CM).error)
            for a, b in pairs
        ]
        cell = cells[name]
        assert cell["direct_mm"] == pytest.approx(10 * np.mean(direct), rel=1e-6)
        assert cell["fitted_never_worse"]
        assert cell["fitted_mm"] <= cell["direct_on_fitted_pairs_mm"] + 1e-5


@pytest.mark.slow
def test_layers_never_rise_when_fitted(setup):
    rig, shapes = setup
    layers, errors = layers_protocol(
        rig, shapes, np.array([[0, 1], [6, 7]]), np.random.default_rng(4), OPTIONS
    )
    assert errors["fitted"].shape == errors["direct"].shape == (2, len(LAYER_SCHEDULE))
    assert layers["fitted_non_increasing_every_pair"] and layers["pairs"] == 2
    np.testing.assert_allclose(layers["direct_mm"], errors["direct"].mean(axis=0))
    assert np.all(np.diff(errors["fitted"], axis=1) <= 0)


@pytest.mark.slow
def test_clip_edit_protocol_keeps_every_frame_and_vertex_outside_the_edit(
    setup, ict_face, livelink_weights
):
    rig, _ = setup
    numbers, run = clip_edit_protocol(rig, ict_face, livelink_weights[90:120], OPTIONS)
    assert numbers["frame"] == run.frame == 15 and len(run.clip) == 30
    lo, hi = numbers["window"]
    assert lo < run.frame < hi and numbers["outside_window_bit_identical"]
    assert numbers["outside_window_max_mm"] == 0.0 and numbers["outside_mask_max_mm"] == 0.0
    assert numbers["outside_mask_vertices"] > 0
    # the fit is never worse than no edit (the clip's frame) in the mouth
    assert numbers["edit_error_mm"] <= numbers["edit_error_before_mm"] + 1e-4
    np.testing.assert_array_equal(run.edited.clip[:lo], run.clip[:lo])


@pytest.mark.slow
def test_dialogue_table_keeps_the_rest_of_the_face_and_inverts_exactly(
    setup, ict_face, livelink_weights
):
    rig, _ = setup
    mouth = expression_region(ict_face, threshold=0.3)
    results, run = dialogue_table(rig, ict_face, livelink_weights, mouth, OPTIONS, 3, seed=0)
    assert run.source.shape == run.target.shape == (3, rig.n_vertices, 3)
    assert results["frames"] == {"source": [90, 92], "target": [135, 137]}
    assert results["rig_inversion_mm"] == 0.0
    assert results["rest_of_face_change_mm"] == results["fitted"]["rest_of_face_change_mm"] == 0
    assert results["mouth_difference_mm"] < results["source_mouth_difference_mm"]
    for name in ("gbs_19", "gbs_ict_53"):
        baseline = results["baselines"][name]
        assert 0 <= baseline["rest_of_face_change_mm"] <= baseline["rest_of_face_change_max_mm"]
    # the 53-expression GBS spans the linear rig's frames: inverted almost exactly
    assert results["baselines"]["gbs_ict_53"]["rig_inversion_mm"] < 0.05


def test_results_of_the_same_pairs_refuses_another_protocol(tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"protocol": {"pairs": 1000}}))  # before the seed was recorded
    assert results_of_the_same_pairs(path, 1000, 0, "--x")["protocol"]["pairs"] == 1000
    with pytest.raises(ValueError, match="--x: pass the --pairs and --seed"):
        results_of_the_same_pairs(path, 1000, 1, "--x")
    with pytest.raises(ValueError, match="--x: "):
        results_of_the_same_pairs(path, 10, 0, "--x")


def test_local_fit_from_selection_needs_the_whole_selection(ict_face):
    with pytest.raises(ValueError, match="selected: .*missing \\['ridge'\\]"):
        local_fit_from_selection(ict_face, np.zeros((4, 53)), {"patches": 300, "basis": 19})


@pytest.mark.parametrize("folder", ["canrig_workflows", "canrig_workflows_local_fit"])
def test_the_committed_tables_render_from_their_results(folder):
    results = json.loads((RESULTS / folder / "results.json").read_text())
    assert workflows_markdown(results) == (RESULTS / folder / "table.md").read_text()
    # before the dialogue script runs: no dialogue rows, no Table 6
    del results["dialogue"], results["timing"]["dialogue_ms_per_frame"]
    text = workflows_markdown(results)
    assert "dialogue" not in text and "Table 6" not in text


@pytest.mark.slow  # loads and prepares the trained network (~10 s)
def test_network_rig_reproduces_the_committed_protocol(ict_quartic):
    checkpoint = RESULTS / "canrig_workflows" / "model" / "checkpoint.eqx"
    rig, model = network_rig(checkpoint, ict_quartic)
    committed = json.loads((RESULTS / "canrig_workflows" / "results.json").read_text())
    model["checkpoint"] = Path(model["checkpoint"]).relative_to(RESULTS.parents[1]).as_posix()
    assert model == committed["protocol"]["model"]
    assert rig.n_vertices == ict_quartic.n_vertices


@pytest.mark.slow
def test_workflow_data_holds_the_held_out_half_and_random_poses(data_dir):
    data = workflow_data(data_dir)
    half = len(data.capture) // 2
    np.testing.assert_array_equal(data.capture_test, data.capture[half:])
    assert data.shapes.shape == (len(data.capture) - half + 100, data.quartic.n_vertices, 3)
    first = evaluate_batch(data.quartic, data.capture_test[:1])
    np.testing.assert_allclose(data.shapes[0], np.asarray(first)[0], atol=1e-5)


@pytest.mark.slow
def test_select_local_fit_keeps_the_best_and_rebuilds_it(ict_quartic, livelink_weights):
    rig, protocol = select_local_fit(ict_quartic, livelink_weights, n_pairs=2, progress=print)
    rows = protocol["selection_on_training_pairs"]
    assert len(rows) == 18 and protocol["selected"] == min(rows, key=lambda r: r["mm"])
    again = local_fit_from_selection(ict_quartic, livelink_weights, protocol["selected"])
    handles = rig.handles(np.arange(0, 9000, 45))
    a, b = np.asarray(ict_quartic.neutral), np.asarray(ict_quartic.neutral) + 0.1
    np.testing.assert_array_equal(
        pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF_PER_CM).shape,
        pose_a_to_b(again, again.handles(np.arange(0, 9000, 45)), a, b, 2.0, 3.0).shape,
    )
