"""The one-standard-error width (``fit_width``) against an independent dense-grid minimum,
and the pieces of the few-edits protocol: temporal change and edit reuse by search."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.papers.wpse import reference_coefficients
from canrig_jax.rig import evaluate_batch
from canrig_jax.wpse import fit_width, prepare_edits, reuse_edits, temporal_change
from canrig_jax.wpse._width import loo_distance_per_edit


def _numpy_loo_distances(metric, poses, displacements, sigma, ridge=1e-6):
    """(P,) mean over vertices of |d_i - prediction of d_i without edit i| by explicit
    float64 refits (no Rippa shortcut)."""
    metric, poses = np.asarray(metric, np.float64), np.asarray(poses, np.float64)
    d = np.asarray(displacements, np.float64)
    out = []
    for i in range(poses.shape[0]):
        keep = np.arange(poses.shape[0]) != i
        x = reference_coefficients(metric, poses[keep], d[:, keep], sigma, ridge)
        r2 = np.einsum("sk,pk->sp", metric, (poses[i] - poses[keep]) ** 2)
        predicted = np.einsum("sp,spc->sc", np.exp(-r2 / (2 * sigma**2)), x)
        out.append(np.linalg.norm(d[:, i] - predicted, axis=-1).mean())
    return np.array(out)


@pytest.fixture(scope="module")
def smooth_data(tiny_rig):
    """9 edits that are a smooth function of the pose (the LOO curve has an interior
    minimum), world axes so the independent check needs no frames."""
    rng = np.random.default_rng(3)
    poses = rng.uniform(0, 1, (9, tiny_rig.n_blendshapes)).astype(np.float32)
    edits = 0.5 * np.tensordot(np.sin(2.0 * poses) ** 2, np.asarray(tiny_rig.deltas), 1)
    return prepare_edits(tiny_rig, poses, edits.astype(np.float32), local_frames=False)


def test_loo_distances_match_explicit_refits(smooth_data):
    args = (smooth_data.metric, smooth_data.poses, smooth_data.displacements)
    for sigma in (0.2, 0.7):
        got = np.asarray(loo_distance_per_edit(smooth_data, sigma))
        np.testing.assert_allclose(got, _numpy_loo_distances(*args, sigma), rtol=2e-3)


def test_fit_width_matches_an_independent_dense_grid(smooth_data):
    """On a 300-point grid of the independent NumPy LOO curve: the LOO minimum lies within
    one step of fit_width's 41-point grid of its loo_min_sigma, and the one-standard-error
    width (smallest width within one SE of the minimum) within one step of its sigma; the
    rule picks a strictly narrower width than the minimum here."""
    fit = fit_width(smooth_data)
    step = fit.grid[1] / fit.grid[0]
    args = (smooth_data.metric, smooth_data.poses, smooth_data.displacements)
    dense = np.geomspace(fit.grid[0], fit.grid[-1], 300)
    per_edit = np.stack([_numpy_loo_distances(*args, s) for s in dense])
    mean = per_edit.mean(axis=1)
    best = int(np.argmin(mean))
    se = per_edit[best].std(ddof=1) / np.sqrt(per_edit.shape[1])
    one_se = dense[np.flatnonzero(mean <= mean[best] + se)[0]]
    assert 1 / step <= fit.loo_min_sigma / dense[best] <= step
    assert 1 / step <= fit.sigma / one_se <= step
    assert fit.sigma < fit.loo_min_sigma / step  # the rule matters on this case
    assert fit.standard_error == pytest.approx(se, rel=0.05)
    # se_factor 0 is the plain LOO minimum
    assert fit_width(smooth_data, se_factor=0.0).sigma == fit.loo_min_sigma


def test_fit_width_does_not_score_the_rest_pose_anchor(tiny_rig, smooth_data):
    poses = np.asarray(smooth_data.poses)
    edits = 0.5 * np.tensordot(np.sin(2.0 * poses) ** 2, np.asarray(tiny_rig.deltas), 1)
    anchored = prepare_edits(tiny_rig, poses, edits.astype(np.float32), rest_pose=True)
    assert anchored.poses.shape[0] == poses.shape[0] + 1
    assert fit_width(anchored).loo_per_edit.shape[1] == poses.shape[0]


def test_fit_width_bad_input(tiny_rig, smooth_data):
    two = prepare_edits(
        tiny_rig, smooth_data.poses[:2], np.zeros((2, tiny_rig.n_vertices, 3), np.float32) + 0.01
    )
    with pytest.raises(ValueError, match="data"):
        fit_width(two)
    with pytest.raises(ValueError, match="se_factor"):
        fit_width(smooth_data, se_factor=-1.0)
    with pytest.raises(ValueError, match="grid"):
        fit_width(smooth_data, grid=np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match="max_vertices"):
        fit_width(smooth_data, max_vertices=0)


def test_temporal_change_of_a_ramp_and_a_jump():
    t = np.arange(10, dtype=np.float64)[:, None, None]
    ramp = np.broadcast_to(t * np.array([0.3, 0.4, 0.0]), (10, 4, 3)).copy()
    change = temporal_change(ramp)
    assert change["max_step"] == pytest.approx(0.5)
    assert change["max_acceleration"] == pytest.approx(0.0, abs=1e-12)
    ramp[6:, 2, 0] += 2.0  # a jump at one vertex between frames 5 and 6
    change = temporal_change(ramp)
    assert change["max_step"] > 2.0
    assert int(np.argmax(change["step"])) == 5
    with pytest.raises(ValueError, match="frames"):
        temporal_change(ramp[:2])
    with pytest.raises(ValueError, match="frames"):
        temporal_change(np.full((5, 2, 3), np.nan))


@pytest.mark.bad_input
def test_reuse_finds_the_matching_edit_and_nothing_far_away(tiny_rig, tiny_edits):
    """A query at a library pose gets that edit back (the found model reproduces its own
    edits); with a threshold below every energy nothing is found and nothing corrected."""
    poses, edits = tiny_edits
    roi = np.arange(tiny_rig.n_vertices)
    query = poses[[2, 4]]
    found = reuse_edits(tiny_rig, poses, edits, query, roi, tau=1e-3, sigma=0.3)
    assert [f.tolist()[:1] for f in found.found] == [[2], [4]]
    np.testing.assert_allclose(found.corrections, edits[[2, 4]], atol=1e-4)
    far = np.asarray(query + 0.5, np.float32)
    none = reuse_edits(tiny_rig, poses, edits, far, roi, tau=1e-3, sigma=0.3)
    assert all(f.size == 0 for f in none.found)
    assert np.all(none.corrections == 0)
    with pytest.raises(ValueError, match="query_poses"):
        reuse_edits(tiny_rig, poses, edits, query[:, :2], roi, tau=1.0, sigma=0.3)
    assert np.asarray(evaluate_batch(tiny_rig, query)).shape == found.corrections.shape
