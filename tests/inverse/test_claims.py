"""Racković et al. 2023's claims on real data: the noisy Live Link take through ict-quartic.

Protocol of the experiment (``experiments/inverse_rig.py``): each method's alpha is chosen on
random sparse training poses only, by ``select_alpha``; the claims are then checked once on
the take, with the paper's numbers (cardinality at least 20 % below the least-squares
baselines, lower RMSE, smoother weight curves than Joshi's).
"""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.inverse import roughness, summarize
from canrig_jax.papers.inverse_rig import select_alpha
from canrig_jax.rig import evaluate_batch, random_sparse_poses

ALPHAS = (0.0, 0.5, 1.0, 2.0, 5.0, 10.0)


def _paper_cd(alpha):
    """Algorithm 1 as published: 5 passes, decreasing order."""
    return inverse.QuarticCD(alpha=alpha, passes=5, tol=0.0, newton=False)


def _weights(problem, targets, method):
    return np.asarray(inverse.solve_sequence(problem, targets, method).weights)


@pytest.fixture(scope="module")
def take(ict_quartic, ict_quartic_problem, livelink_weights):
    rig, problem = ict_quartic, ict_quartic_problem
    rng = np.random.default_rng(1)
    train = random_sparse_poses(rng, 30, rig.names)
    clean, clean_train = (np.asarray(evaluate_batch(rig, w)) for w in (livelink_weights, train))
    noise = np.sqrt(0.03)
    noisy = clean + rng.normal(0, noise, clean.shape).astype(np.float32)
    noisy_train = clean_train + rng.normal(0, noise, clean_train.shape).astype(np.float32)
    return rig, problem, clean, noisy, clean_train, noisy_train


def _chosen_alpha(take, make, name):
    rig, problem, _, _, clean_train, noisy_train = take
    sweep = [
        {"alpha": a, **summarize(rig, _weights(problem, noisy_train, make(a)), clean_train)}
        for a in ALPHAS
    ]
    return select_alpha(sweep, method=name)["alpha"]


@pytest.mark.slow
def test_quartic_cd_is_more_accurate_than_linear_cd_and_seol(take):
    rig, problem, clean, noisy, *_ = take
    rmse = {
        name: summarize(rig, _weights(problem, noisy, method), clean)["rmse_mean_mm"]
        for name, method in {
            "quartic": _paper_cd(0.5),
            "linear": inverse.LinearCD(alpha=0.5, passes=5, tol=0.0, newton=False),
            "seol": inverse.Seol(),
        }.items()
    }
    assert rmse["quartic"] < rmse["linear"] and rmse["quartic"] < rmse["seol"], rmse


@pytest.mark.slow  # 14 s; the inverse experiment's committed table shows the same claim
def test_tradeoff_claim_sparser_and_more_accurate_than_joshi_and_cetinaslan(take):
    """With alpha chosen on training poses only: QuarticCD (5 passes) has a lower mean RMSE
    than Joshi and Cetinaslan, a cardinality at least 20 % below each, and a lower roughness
    than Joshi."""
    rig, problem, clean, noisy, *_ = take
    alpha_cd = _chosen_alpha(take, _paper_cd, "quartic_cd")
    alpha_ridge = _chosen_alpha(take, lambda a: inverse.Cetinaslan(alpha=a), "cetinaslan")
    weights = {
        "quartic_cd": _weights(problem, noisy, _paper_cd(alpha_cd)),
        "joshi": _weights(problem, noisy, inverse.Joshi()),
        "cetinaslan": _weights(problem, noisy, inverse.Cetinaslan(alpha=alpha_ridge)),
    }
    scores = {name: summarize(rig, w, clean) for name, w in weights.items()}
    cd = scores["quartic_cd"]
    for baseline in ("joshi", "cetinaslan"):
        assert cd["rmse_mean_mm"] < scores[baseline]["rmse_mean_mm"], (alpha_cd, scores)
        assert cd["cardinality"] <= 0.8 * scores[baseline]["cardinality"], (alpha_cd, scores)
    assert roughness(weights["quartic_cd"]) < roughness(weights["joshi"])


@pytest.mark.slow  # 12-21 s; the default run stays under 10 min on 2 cores
def test_random_order_gives_rough_weight_curves(take):
    """Table 8: a random coordinate order, drawn afresh for every frame, makes the weight
    curves of a take rougher than the fixed decreasing order (one permutation for the whole
    take, as before issue 22, could not show this)."""
    rig, problem, clean, noisy, *_ = take
    fixed = _weights(problem, noisy, _paper_cd(5.0))
    random = np.asarray(
        inverse.solve_sequence(
            problem, noisy, inverse.QuarticCD(alpha=5.0, passes=5, tol=0.0, newton=False,
                                              order="random")
        ).weights
    )  # fmt: skip
    assert roughness(random) > 5 * roughness(fixed), (roughness(random), roughness(fixed))
