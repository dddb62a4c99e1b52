"""The sparsity protocol's rule and verdict (``canrig_jax.papers.inverse_rig``) on hand-made
sweeps, and its noisy training meshes on the synthetic rig (no data folder)."""

import numpy as np
import pytest

from canrig_jax.papers import inverse_rig
from canrig_jax.rig import BlendshapeRig, evaluate_batch


def _row(alpha, rmse, cardinality=10.0):
    return {"alpha": alpha, "rmse_mean_mm": rmse, "cardinality": cardinality}


def test_rule_takes_the_largest_alpha_within_the_limit_not_the_last_row_within_it():
    # training RMSE is not monotone in alpha (the L1 term also filters noise)
    sweep = [_row(0.0, 0.30), _row(1.0, 0.20), _row(5.0, 0.45), _row(2.0, 0.39), _row(10.0, 0.6)]
    assert inverse_rig.sparsest_alpha_within(sweep, 0.40)["alpha"] == 2.0
    assert inverse_rig.sparsest_alpha_within(sweep, 0.45)["alpha"] == 5.0  # equal RMSE qualifies
    assert inverse_rig.sparsest_alpha_within(sweep, 0.19) is None  # none that accurate


def test_rule_refuses_a_failed_solve():
    with pytest.raises(ValueError, match=r"alpha \[1.0\]"):
        inverse_rig.sparsest_alpha_within([_row(0.0, 0.3), _row(1.0, float("nan"))], 0.4)
    with pytest.raises(ValueError, match="rmse_limit_mm"):
        inverse_rig.sparsest_alpha_within([_row(0.0, 0.3)], float("nan"))


def test_verdict_needs_the_reduction_against_every_baseline_and_no_higher_rmse():
    baselines = {"joshi": _row(0.0, 0.25, 40.0), "cetinaslan": _row(2.0, 0.24, 36.0)}
    met = inverse_rig.sparsity_verdict(_row(1.0, 0.20, 30.0), baselines)
    assert met["met"] and met["reduction"]["cetinaslan"] == pytest.approx(1 - 30 / 36)
    # 15 % below Joshi but only 11 % below Cetinaslan
    assert not inverse_rig.sparsity_verdict(_row(1.0, 0.20, 32.0), baselines)["met"]
    # sparse enough, but less accurate than Cetinaslan
    worse = inverse_rig.sparsity_verdict(_row(5.0, 0.245, 20.0), baselines)
    assert not worse["met"] and worse["rmse_at_most"] == {"joshi": True, "cetinaslan": False}


def test_noisy_meshes_add_the_stated_variance_in_the_rigs_unit(synthetic_rig):
    rig = synthetic_rig
    in_dm = BlendshapeRig(rig.neutral / 10, rig.deltas / 10, (), rig.names, rig.faces, units="dm")
    weights = np.random.default_rng(0).uniform(0, 1, (200, rig.n_blendshapes))
    for case, cm_per_unit in ((rig, 1.0), (in_dm, 10.0)):
        clean, noisy = inverse_rig.noisy_meshes(case, weights, np.random.default_rng(1), 0.03)
        np.testing.assert_allclose(clean, np.asarray(evaluate_batch(case, weights)), atol=1e-6)
        variance_cm2 = np.var((noisy - clean) * cm_per_unit)
        assert variance_cm2 == pytest.approx(0.03, rel=0.02), variance_cm2
