"""The temporal inverse rig's smoothness rule and scores (``papers.inverse_rig``): synthetic
training takes, the rule on hand-made sweeps, the validation split and its table, the targets
and the rows and curve against direct computations."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.papers import inverse_rig
from canrig_jax.rig import evaluate

ALPHA = 0.5


@pytest.fixture(scope="module")
def take(synthetic_rig):
    """(problem, noisy targets (T, V, 3), clean weights (T, K)): smooth, sparse weight curves
    on the synthetic rig, noise of variance 0.03 cm^2."""
    rng = np.random.default_rng(5)
    frames, k = 16, synthetic_rig.n_blendshapes
    time = np.linspace(0.0, 1.0, frames)[:, None]
    phase, speed = rng.uniform(0, 1, (1, k)), rng.uniform(0.5, 1.5, (1, k))
    weights = np.clip(0.5 + 0.6 * np.sin(2 * np.pi * (speed * time + phase)), 0.0, 1.0)
    weights[weights < 0.3] = 0.0
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(synthetic_rig, weights))
    noisy = (clean + rng.normal(0, np.sqrt(0.03), clean.shape)).astype(np.float32)
    return inverse.prepare(synthetic_rig), noisy, weights


def test_smooth_training_takes_and_the_smoothness_rule():
    names = [f"shape{i}" for i in range(20)]
    takes = inverse_rig.smooth_training_takes(np.random.default_rng(0), names, 2, 90, 60.0)
    assert takes.shape == (2, 90, 20) and takes.min() >= 0 and takes.max() <= 1
    # cosine-eased between keys >= 0.2 s (12 frames) apart: second differences stay below
    # (pi / 12)^2 / 2 = 0.034, where independent random poses jump by up to 2
    assert np.abs(np.diff(takes, n=2, axis=1)).max() < 0.05
    active = (takes[:, 0] > 0).sum(axis=1)  # the first frame is a key pose: 4 to 10 active
    assert np.all((active >= 4) & (active <= 10))
    sweep = [
        {"smoothness": 0.0, "rmse_mean_mm": 1.0},
        {"smoothness": 10.0, "rmse_mean_mm": 0.9},
        {"smoothness": 100.0, "rmse_mean_mm": 1.04},
        {"smoothness": 1000.0, "rmse_mean_mm": 1.2},
    ]
    assert inverse_rig.select_smoothness(sweep)["smoothness"] == 100.0
    with pytest.raises(ValueError, match="sweep"):
        inverse_rig.select_smoothness([{"smoothness": 1.0, "rmse_mean_mm": 1.0}])
    with pytest.raises(ValueError, match="fps"):
        inverse_rig.smooth_training_takes(
            np.random.default_rng(0), ["a", "b", "c", "d"], 1, 10, 0.0
        )


def _modes(temporal_roughness, temporal_rmse):
    """Hand-made ``temporal_row``s: warm start roughness 4, truth 1, per-frame RMSE 2 mm."""
    return {
        "truth": {"roughness": 1.0, "rmse_mm": 0.0},
        "per_frame": {"roughness": 8.0, "rmse_mm": 2.0},
        "warm_start": {"roughness": 4.0, "rmse_mm": 2.2},
        "temporal": {"roughness": temporal_roughness, "rmse_mm": temporal_rmse},
    }


def test_temporal_targets_are_ratios_against_their_limits():
    at_limits = inverse_rig.temporal_targets(_modes(2.0, 2.1))  # 0.5x, 2x, 1.05x
    assert at_limits["roughness_vs_warm_start"] == 0.5 and at_limits["roughness_vs_truth"] == 2.0
    assert at_limits["rmse_vs_per_frame"] == pytest.approx(1.05) and at_limits["met"]
    assert not inverse_rig.temporal_targets(_modes(2.0, 2.2))["met"]  # RMSE 1.1x per-frame
    assert not inverse_rig.temporal_targets(_modes(2.4, 2.0))["met"]  # roughness 0.6x warm start
    assert not inverse_rig.temporal_targets(_modes(2.0, 2.0), roughness_vs_truth=1.5)["met"]
    with pytest.raises(ValueError, match="modes"):
        inverse_rig.temporal_targets({"temporal": {"roughness": 1.0, "rmse_mm": 1.0}})


def _rmse_mm(rig, weights, clean):
    """Mean over frames of sqrt(mean over vertices of the squared error), mm (a rig in cm)."""
    meshes = np.asarray(jax.vmap(evaluate, (None, 0))(rig, np.asarray(weights, np.float32)))
    return np.sqrt(((meshes - clean) ** 2).sum(-1).mean(-1)).mean() * 10.0


@pytest.mark.slow
def test_temporal_row_and_smoothness_curve_match_direct_computations(synthetic_rig, take):
    problem, targets, weights = take
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(synthetic_rig, weights.astype(np.float32)))
    row = inverse_rig.temporal_row(synthetic_rig, weights, targets, seconds=0.002)
    second = weights[2:] - 2 * weights[1:-1] + weights[:-2]
    np.testing.assert_allclose(row["rmse_mm"], _rmse_mm(synthetic_rig, weights, targets), rtol=1e-4)
    np.testing.assert_allclose(row["roughness"], (second**2).sum(), rtol=1e-12)
    assert row["ms_per_frame"] == pytest.approx(2.0)
    assert inverse_rig.temporal_row(synthetic_rig, weights, clean)["ms_per_frame"] is None

    rows = []  # two takes: the take and the take backwards (the same shapes as above)
    takes, cleans = [targets, targets[::-1]], [clean, clean[::-1]]
    curve = inverse_rig.smoothness_curve(
        problem, takes, cleans, ALPHA, (0.0, 20.0), on_row=rows.append
    )
    assert rows == curve and [r["smoothness"] for r in curve] == [0.0, 20.0]
    for r, method in zip(
        curve,
        (inverse.QuarticNewton(alpha=ALPHA), inverse.TemporalNewton(alpha=ALPHA, smoothness=20.0)),
        strict=True,
    ):
        runs = [np.asarray(inverse.solve_sequence(problem, b, method).weights) for b in takes]
        rmse = [_rmse_mm(synthetic_rig, w, c) for w, c in zip(runs, cleans, strict=True)]
        np.testing.assert_allclose(r["rmse_mean_mm"], np.mean(rmse), rtol=1e-4)
        rough = [(np.diff(w.astype(np.float64), n=2, axis=0) ** 2).sum() for w in runs]
        np.testing.assert_allclose(r["roughness"], np.mean(rough), rtol=1e-6)
    with pytest.raises(ValueError, match="grid_cm2"):
        inverse_rig.smoothness_curve(problem, takes, cleans, ALPHA, (1.0,))
    with pytest.raises(ValueError, match="targets"):
        inverse_rig.smoothness_curve(problem, takes, cleans[:1], ALPHA, (0.0,))


def test_validation_split_halves_and_the_split_table():
    from canrig_jax.papers.inverse_rig import validation_split_table

    assert inverse_rig.validation_split(10) == (slice(0, 5), slice(5, 10))
    assert inverse_rig.validation_split(7) == (slice(0, 3), slice(3, 7))
    with pytest.raises(ValueError, match="n_frames"):
        inverse_rig.validation_split(5)
    curve = [
        {"smoothness": 0.0, "rmse_mean_mm": 2.0, "roughness": 8.0},
        {"smoothness": 10.0, "rmse_mean_mm": 1.8, "roughness": 2.0},
        {"smoothness": 100.0, "rmse_mean_mm": 2.08, "roughness": 0.5},
    ]
    protocol = {
        "alpha_cm2": 0.5,
        "smoothness_cm2": 100.0,
        "smoothness_rig_units": 100.0,
        "smoothness_chosen_on": "ict validation half",
        "validation_frames": [0, 4],
        "test_frames": [5, 9],
        "validation_curve": curve,
        "targets": inverse_rig.temporal_targets(_modes(2.0, 2.1)),
    }
    modes = {
        m: {**r, "p95_mm": 1.0, "cardinality": 3.0, "ms_per_frame": None}
        for m, r in _modes(2.0, 2.1).items()
    }
    text = validation_split_table({"ict": {"protocol": protocol, "modes": modes}}, "the rule")
    # lowest validation RMSE at 10 (1.8 / 2.0 = 0.9x); chosen 100 (2.08 / 2.0 = 1.04x)
    assert (
        "lowest at 10 cm^2 (0.900x per-frame)" in text and "within 5 %, 100 cm^2 (1.040x)" in text
    )
    assert "| temporal | 2.1 | 1 | 3 | 2 | – |" in text and "(both cases): ict met." in text
