"""The WPSE experiment's protocols on a tiny rig: each result checked against an independent
computation or an invariant of the protocol."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canrig_jax import wpse
from canrig_jax.papers import wpse as wpse_paper
from canrig_jax.rig import evaluate, evaluate_batch
from canrig_jax.wpse._pse import correction

from ...wpse.conftest import grid_rig

VARIANTS = ("pse", "wpse", "wpse_rest_pose", "wpse_global_frames")
RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results" / "wpse"


def _sculpt_of(rig):
    """A made-up nonlinear wanted mesh: the linear one plus bumps growing with products of
    weights (so pairs of channels need fix shapes). Takes (K,) or (T, K) weights."""
    bump = np.sin(3 * np.asarray(rig.neutral)) * 0.05

    def sculpt(weights):
        w = np.atleast_2d(np.asarray(weights, np.float32))
        linear = np.asarray(evaluate_batch(rig, w))
        amount = w[:, 0] * w[:, 1] + w[:, 2] ** 2 + w[:, 3] * w[:, 4]
        meshes = linear + amount[:, None, None] * bump
        return meshes[0] if np.ndim(weights) == 1 else meshes

    return sculpt


@pytest.fixture(scope="module")
def take():
    """A 6-channel grid rig, 24 random frames, the wanted and linear meshes, 5 edit frames."""
    rig = grid_rig(n=6, n_blendshapes=6, seed=3)
    rng = np.random.default_rng(4)
    poses = rng.uniform(0.0, 1.0, (24, rig.n_blendshapes)).astype(np.float32)
    sculpt = _sculpt_of(rig)
    desired = sculpt(poses).astype(np.float32)
    linear = np.asarray(evaluate_batch(rig, poses))
    error = np.linalg.norm(desired - linear, axis=2).mean(axis=1)
    edit_frames = wpse_paper.select_edit_frames(error, poses, 5, 0.3)
    held_out = np.setdiff1d(np.arange(len(poses)), edit_frames)
    return {
        "rig": rig,
        "sculpt": sculpt,
        "frames": (poses, desired, linear),
        "edit_frames": edit_frames,
        "held_out": held_out,
    }


@pytest.fixture(scope="module")
def compared(take):
    """compare_methods at two budgets (fits every variant's LOO width: slow tests only)."""
    poses, desired, linear = take["frames"]
    return wpse_paper.compare_methods(
        take["rig"],
        *take["frames"],
        take["edit_frames"],
        take["held_out"],
        budgets=(3, 5),
        sculpt=take["sculpt"],
        others={"shifted": desired[take["held_out"]] + np.float32(0.01)},
    )


def test_error_summary_of_known_displacements():
    rng = np.random.default_rng(0)
    desired = rng.normal(size=(3, 50, 3))
    length = rng.uniform(0.0, 2.0, (3, 50))  # cm
    direction = rng.normal(size=(3, 50, 3))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    summary, err = wpse_paper.error_summary(desired + length[..., None] * direction, desired)
    np.testing.assert_allclose(err, 10 * length, rtol=1e-12)
    assert summary["mean_mm"] == pytest.approx(10 * length.mean())
    assert summary["max_mm"] == pytest.approx(10 * length.max())
    assert summary["p95_mm"] == pytest.approx(10 * np.sort(length.ravel())[int(0.95 * 149)], 0.02)


@pytest.mark.slow
def test_compare_methods_scores_every_method_at_every_budget(take, compared):
    poses, desired, linear = take["frames"]
    held_out = take["held_out"]
    assert list(compared.errors) == ["linear", *VARIANTS, "fsm", "shifted"]
    linear_err = np.linalg.norm(linear[held_out] - desired[held_out], axis=2) * 10
    for key in ("p3", "p5"):
        assert compared.errors["linear"][key]["mean_mm"] == pytest.approx(linear_err.mean())
        # every vertex of the shifted meshes is sqrt(3) * 0.01 cm off
        shifted = compared.errors["shifted"][key]
        assert shifted["max_mm"] == pytest.approx(10 * np.sqrt(3) * 0.01, rel=1e-5)
        # with the edits the WPSE variants beat the linear rig on frames never sculpted
        assert compared.errors["wpse"][key]["mean_mm"] < linear_err.mean()
    assert compared.maps["wpse"].shape == (held_out.size, take["rig"].n_vertices)
    assert set(compared.models) == {(m, b) for m in (*VARIANTS, "fsm") for b in (3, 5)}


@pytest.mark.slow
def test_compare_methods_sweep_passes_through_the_loo_width(compared):
    """The oracle sweep includes the leave-one-out width itself, where it must give the
    held-out error of the model compare_methods scored."""
    for method in ("pse", "wpse"):
        for key in ("p3", "p5"):
            width = compared.sigma[f"{method}_{key}"]["loo_sigma"]
            points = dict(compared.sweep[f"{method}_{key}"])
            assert len(points) == 7
            at_width = min(points, key=lambda s: abs(s - width))
            assert at_width == pytest.approx(width, rel=1e-6)
            mean = compared.errors[method][key]["mean_mm"]
            assert points[at_width] == pytest.approx(mean, rel=1e-5)


@pytest.mark.slow
def test_compare_methods_rest_pose_variant_is_zero_at_rest(compared):
    for key in ("p3", "p5"):
        assert compared.rest_correction[f"wpse_rest_pose_{key}"] < 1e-3
        assert compared.rest_correction[f"wpse_{key}"] > 1e-2


@pytest.mark.slow  # 5-20 s of compilation
def test_few_edit_errors_use_the_given_and_the_one_se_widths(take):
    rig, (poses, desired, linear) = take["rig"], take["frames"]
    edit_frames, held_out = take["edit_frames"], take["held_out"]
    rows, widths = wpse_paper.few_edit_errors(
        rig,
        *take["frames"],
        edit_frames,
        held_out,
        budgets=(4,),
        known_sigma={"pse_p4": 0.5, "wpse_p4": 0.37},
    )
    row = rows["4"]
    assert list(row) == ["linear", "pse", "wpse", "wpse_new_width", "wpse_new_width_rest_pose"]
    assert (row["pse"]["sigma"], row["wpse"]["sigma"]) == (0.5, 0.37)
    chosen = edit_frames[:4]
    edits = desired[chosen] - linear[chosen]
    data = wpse.prepare_edits(rig, poses[chosen], edits)
    assert row["wpse_new_width"]["sigma"] == pytest.approx(wpse.fit_width(data).sigma)
    assert widths["wpse_new_width_p4"]["sigma"] == row["wpse_new_width"]["sigma"]
    # the one-SE width: the smallest within one standard error of the LOO minimum
    w = widths["wpse_new_width_p4"]
    assert w["sigma"] <= w["loo_min_sigma"]
    assert w["loo_mean_at_min_mm"] <= w["loo_mean_at_sigma_mm"]
    assert w["loo_mean_at_sigma_mm"] <= w["loo_mean_at_min_mm"] + w["standard_error_mm"] + 1e-9
    size = np.linalg.norm(edits, axis=2).mean() * 10
    assert w["no_correction_mm"] == pytest.approx(size, rel=1e-6)
    model = wpse.fit_prepared(data, 0.37)
    meshes = wpse_paper.apply_frames(model, poses[held_out], linear[held_out])
    err = np.linalg.norm(meshes - desired[held_out], axis=2) * 10
    assert row["wpse"]["mean_mm"] == pytest.approx(err.mean(), rel=1e-6)


def test_temporal_smoothness_edits_the_worst_frame_and_reproduces_it(take):
    rig, (_, desired, linear) = take["rig"], take["frames"]
    take_frames = np.arange(12)
    summary, curves = wpse_paper.temporal_smoothness(
        rig, *take["frames"], take["edit_frames"], take_frames, sigma=0.5
    )
    candidates = [f for f in take_frames if f not in set(take["edit_frames"])]
    error = [np.linalg.norm(desired[f] - linear[f], axis=1).mean() for f in candidates]
    frame = candidates[int(np.argmax(error))]
    assert summary["edited_frame"] == frame
    # one edit: exact at its own pose
    wanted = np.linalg.norm(desired[frame] - linear[frame], axis=1).max() * 10
    assert curves["size"][frame] == pytest.approx(wanted, rel=1e-3)
    assert summary["max_correction_mm"] >= curves["size"][frame] - 1e-9
    steps = np.linalg.norm(np.diff(desired[take_frames], axis=0), axis=2).max(axis=1) * 10
    np.testing.assert_allclose(curves["take_step"], steps, rtol=1e-5)
    assert curves["step"].shape == (11,)


def test_channel_region_of_disjoint_channel_sets_are_disjoint(take):
    rig = take["rig"]
    regions = [wpse_paper.channel_region(rig, c) for c in ([0, 1], [2, 3], [4, 5])]
    assert sum(r.size for r in regions) == np.unique(np.concatenate(regions)).size
    alpha = wpse.blendshape_metric(rig.deltas)
    np.testing.assert_array_equal(regions[0], np.flatnonzero(alpha[:, 0] + alpha[:, 1] > 0.5))
    everything = wpse_paper.channel_region(rig, np.arange(rig.n_blendshapes))
    np.testing.assert_array_equal(everything, np.arange(rig.n_vertices))


@pytest.mark.slow
def test_reuse_by_search_larger_tau_finds_more(take):
    rig, (_, desired, linear) = take["rig"], take["frames"]
    out = wpse_paper.reuse_by_search(
        rig,
        *take["frames"],
        np.arange(20),
        region_channels=[0, 1, 2],
        library_size=4,
        min_distance=0.2,
        tau_scales=(1.0, 0.5, 1.5),
    )
    assert all(f < 10 for f in out["library_frames"])
    assert out["query_frames"] == [10, 19]
    assert out["tau"] == pytest.approx(2 * out["sigma"] * out["roi_vertices"])
    assert out["tau_x0.5"]["tau"] == pytest.approx(0.5 * out["tau"])
    found = [out["tau_x0.5"], out, out["tau_x1.5"]]
    counts = [r["frames_with_edits_found"] for r in found]
    means = [r["mean_edits_found"] for r in found]
    assert counts == sorted(counts) and means == sorted(means)
    before = np.linalg.norm(linear[10:20] - desired[10:20], axis=2).mean() * 10
    assert out["error_before_mm"] == pytest.approx(before)


@pytest.mark.bad_input
def test_time_edit_model_row_describes_the_model(take):
    rig, (poses, desired, linear) = take["rig"], take["frames"]
    chosen = take["edit_frames"][:3]
    edits = desired[chosen] - linear[chosen]
    row = wpse_paper.time_edit_model(
        rig, poses[chosen], edits, poses[:4], sigma=0.4, support_tol=1e-4
    )
    model = wpse.fit_pose_space_edit(rig, poses[chosen], edits, sigma=0.4, support_tol=1e-4)
    assert row["edited_vertices"] == model.vertices.shape[0]
    assert (row["vertices"], row["edits"]) == (rig.n_vertices, 3)
    assert row["max_abs_diff_vs_numpy_cm"] < 1e-4
    with pytest.raises(ValueError, match="probe"):
        wpse_paper.time_edit_model(rig, poses[chosen], edits, poses[:4, :2], sigma=0.4)


def test_results_table_reproduces_the_committed_table():
    results = json.loads((RESULTS / "results.json").read_text())
    committed = (RESULTS / "table.md").read_text()
    assert wpse_paper.results_table(results) == committed
    without = wpse_paper.results_table({k: v for k, v in results.items() if k != "timing"})
    timing_lines = [line for line in committed.splitlines() if line.startswith("| face")]
    assert timing_lines and not any(line in without for line in timing_lines)
    assert without.splitlines()[:5] == committed.splitlines()[:5]


@pytest.fixture(scope="module")
def models(take):
    """PSE, WPSE and WPSE pinned at rest of the first 5 edits (width 0.4), and the FSM rig."""
    rig, (poses, desired, linear) = take["rig"], take["frames"]
    chosen = take["edit_frames"]
    edits = desired[chosen] - linear[chosen]
    fit = {
        "pse": {"metric": "euclidean"},
        "wpse": {},
        "wpse_rest_pose": {"rest_pose": True},
    }
    out = {
        name: wpse.fit_pose_space_edit(rig, poses[chosen], edits, sigma=0.4, **options)
        for name, options in fit.items()
    }
    pairs = wpse.coactivation_pairs(poses, 5, rig.names)
    out["fsm"] = wpse.fix_shape_rig(rig, pairs, take["sculpt"])
    return out


def test_rest_pose_correction_is_zero_for_the_pinned_model(take, models):
    rig = take["rig"]
    assert wpse_paper.rest_pose_correction_mm(models["wpse_rest_pose"], rig) < 1e-3
    rest = np.zeros(rig.n_blendshapes, np.float32)
    plain = np.asarray(correction(models["wpse"], rest, evaluate(rig, rest)))
    expected = np.linalg.norm(plain, axis=1).max() * 10
    assert expected > 1e-2
    assert wpse_paper.rest_pose_correction_mm(models["wpse"], rig) == pytest.approx(expected)


@pytest.mark.slow
def test_locality_probe_keeps_everything_when_nothing_changes(take, models):
    """With no channel redrawn every probe is the edited pose: all is retained."""
    poses, _, linear = take["frames"]
    out = wpse_paper.locality_probe(
        take["rig"],
        {m: models[m] for m in ("pse", "wpse")},
        poses,
        take["edit_frames"],
        linear,
        take["sculpt"],
        np.random.default_rng(0),
        eye_channels=[],
        mouth_channels=[0, 1, 2],
        draws=3,
        min_correction_mm=0.0,
    )
    assert out["probes"] == 3 * take["edit_frames"].size
    for name in ("pse", "wpse", "desired"):
        assert out[f"{name}_retained"] == pytest.approx(1.0, abs=1e-5)
    changed = wpse_paper.locality_probe(
        take["rig"],
        {"wpse": models["wpse"]},
        poses,
        take["edit_frames"],
        linear,
        take["sculpt"],
        np.random.default_rng(0),
        eye_channels=[3, 4, 5],
        mouth_channels=[0, 1, 2],
        draws=3,
        min_correction_mm=0.0,
    )
    assert changed["wpse_retained"] != pytest.approx(1.0, abs=1e-3)
    assert changed["eye_channels"] == 3


@pytest.mark.slow
def test_overshoot_sweep_fix_shape_and_corner_edit_are_exact_at_the_corner(take, models):
    summary, curves = wpse_paper.overshoot_sweep(
        take["rig"],
        models["fsm"],
        {"wpse_p5": models["wpse"], "wpse_rest_pose_p5": models["wpse_rest_pose"]},
        take["sculpt"],
        sigma=0.4,
    )
    table = models["fsm"].corrective(2)
    sizes = np.linalg.norm(np.asarray(table.deltas), axis=2).max(axis=1)
    pair = np.asarray(table.indices[int(np.argmax(sizes))])
    assert summary["pair"] == [take["rig"].names[i] for i in pair]
    at = summary["max_correction_mm"]
    assert list(at) == ["desired", "fsm", "wpse_corner_edit", "wpse_p5", "wpse_rest_pose_p5"]
    assert at["desired"]["t=0.0"] == pytest.approx(0.0, abs=1e-5)
    assert at["fsm"]["t=0.0"] == 0.0
    assert at["wpse_rest_pose_p5"]["t=0.0"] < 1e-3
    for curve in ("fsm", "wpse_corner_edit"):
        assert at[curve]["t=1.0"] == pytest.approx(at["desired"]["t=1.0"], rel=1e-3)
    assert curves["desired"].shape == (31,)
    assert curves["fsm"][20] == at["fsm"]["t=1.0"]


@pytest.mark.slow  # 5-20 s of compilation
def test_layering_probe_layers_reproduce_the_latest_sculpt_without_overshoot(take):
    poses = take["frames"][0]
    out = wpse_paper.layering_probe(
        take["rig"], poses[take["edit_frames"][0]], take["sculpt"], sigma=0.4
    )
    assert out["pose_distance"] == pytest.approx(0.05, rel=1e-5)
    assert out["layer_sigma"] == pytest.approx(0.04)
    assert out["n_layers"] == 2
    single, layered = out["single_layer"], out["layered"]
    # one layer interpolates both sculpts, so it swings far past them along the line
    assert max(single["edit_a_max_mm"], single["edit_b_max_mm"]) < 0.05 * out["largest_sculpt_mm"]
    assert single["max_correction_on_line_mm"] > out["largest_sculpt_mm"]
    # layers: the latest sculpt wins where both apply, and nothing exceeds the sculpts
    assert layered["edit_b_max_mm"] < 0.05 * out["largest_sculpt_mm"]
    assert layered["max_correction_on_line_mm"] <= out["largest_sculpt_mm"] * 1.001


def test_search_by_region_keeps_the_library_below_the_percentile(take):
    rig, poses = take["rig"], take["frames"][0]
    library, query = poses[:15], poses[20]
    found = wpse_paper.search_by_region(
        rig, library, query, {"a": [0, 1, 2], "b": [3, 4, 5]}, percentile=40.0
    )
    alpha = wpse.blendshape_metric(rig.deltas)
    for name, channels in (("a", [0, 1, 2]), ("b", [3, 4, 5])):
        roi = found[name]["roi"]
        np.testing.assert_array_equal(roi, wpse_paper.channel_region(rig, channels))
        diff = (query[None, :] - library) ** 2  # (N, K)
        energy = np.sqrt(alpha[roi] @ diff.T).sum(axis=0)  # E of eq. 7, each library pose
        assert found[name]["tau"] == pytest.approx(np.percentile(energy, 40.0), rel=1e-4)
        hits = found[name]["found"]
        expected = np.flatnonzero(energy < found[name]["tau"])
        assert sorted(hits.indices.tolist()) == sorted(expected.tolist())
        assert np.all(np.diff(hits.energies) >= 0)


@pytest.mark.bad_input
def test_protocols_name_the_bad_argument(take, models):
    rig, frames = take["rig"], take["frames"]
    edit_frames, held_out = take["edit_frames"], take["held_out"]
    with pytest.raises(ValueError, match="budgets"):
        wpse_paper.compare_methods(
            rig, *frames, edit_frames, held_out, budgets=(9,), sculpt=take["sculpt"]
        )
    with pytest.raises(ValueError, match="budgets"):
        wpse_paper.few_edit_errors(rig, *frames, edit_frames, held_out, budgets=(0, 3))
    with pytest.raises(ValueError, match="draws"):
        wpse_paper.locality_probe(
            rig,
            {"wpse": models["wpse"]},
            frames[0],
            edit_frames,
            frames[2],
            take["sculpt"],
            np.random.default_rng(0),
            eye_channels=[3],
            mouth_channels=[0],
            draws=0,
        )
    with pytest.raises(ValueError, match="t:"):
        wpse_paper.overshoot_sweep(rig, models["fsm"], {}, take["sculpt"], sigma=0.4, t=[0.0, 1.0])
