"""Inverse-rig solvers on the real ict-quartic rig driven by the real Live Link capture."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.data import load_livelinkface
from canrig_jax.rig import evaluate, ict_quartic_rig


@pytest.fixture(scope="module")
def setup():
    rig, _ = ict_quartic_rig(progress=False)
    weights = load_livelinkface().weights_for(rig.names, missing="zero")[::12]  # 15 frames
    targets = jax.jit(jax.vmap(evaluate, (None, 0)))(rig, weights)
    return rig, inverse.prepare(rig), weights, targets


def _solve_all(problem, targets, method):
    return jax.jit(jax.vmap(lambda b: inverse.solve(problem, b, method)))(targets)


def _rmse_mm(rig, weights, targets):
    meshes = jax.vmap(evaluate, (None, 0))(rig, weights)
    return float(np.sqrt(((np.asarray(meshes) - np.asarray(targets)) ** 2).sum(-1).mean()) * 10)


def test_every_coordinate_update_does_not_increase_the_objective(setup):
    rig, problem, _, targets = setup
    solution = _solve_all(problem, targets[:4], inverse.QuarticCD(alpha=0.5, passes=3, trace=True))
    history = np.asarray(solution.history, np.float64)
    assert history.shape == (4, 3 * rig.n_blendshapes)
    assert np.all(np.diff(history, axis=1) <= 1e-5 * np.abs(history[:, :-1]) + 1e-6)
    # the Gram-space objective agrees with the vertex-space one at the end
    np.testing.assert_allclose(history[:, -1], np.asarray(solution.objective), rtol=1e-3)


def test_linear_cd_one_pass_no_bound_no_l1_equals_seol(setup):
    _, problem, _, targets = setup
    cd = _solve_all(problem, targets, inverse.LinearCD(alpha=0.0, passes=1, upper=jnp.inf))
    seol = _solve_all(problem, targets, inverse.Seol())
    np.testing.assert_allclose(np.asarray(cd.weights), np.asarray(seol.weights), atol=2e-4)


def test_noise_free_targets_are_recovered_well_under_a_tenth_of_a_mm(setup):
    rig, problem, _, targets = setup
    solution = _solve_all(problem, targets[:5], inverse.QuarticCD(alpha=0.0, passes=60))
    assert _rmse_mm(rig, solution.weights, targets[:5]) < 0.05


def test_quartic_cd_beats_linear_cd_and_seol_on_the_take(setup):
    rig, problem, _, targets = setup
    rmse = {
        name: _rmse_mm(rig, _solve_all(problem, targets, method).weights, targets)
        for name, method in {
            "quartic": inverse.QuarticCD(alpha=0.5, passes=5),
            "linear": inverse.LinearCD(alpha=0.5, passes=5),
            "seol": inverse.Seol(),
        }.items()
    }
    assert rmse["quartic"] < rmse["linear"] < rmse["seol"], rmse


def test_closed_form_baselines_match_numpy(setup):
    rig, problem, _, targets = setup
    shapes = np.asarray(rig.deltas, np.float64).reshape(rig.n_blendshapes, -1).T
    offsets = (np.asarray(targets, np.float64) - np.asarray(rig.neutral)).reshape(len(targets), -1)
    joshi = np.clip(np.linalg.lstsq(shapes, offsets.T, rcond=None)[0].T, 0, 1)
    alpha = 0.5
    system = shapes.T @ shapes + 2 * alpha * np.eye(rig.n_blendshapes)
    cetinaslan = np.clip(np.linalg.solve(system, shapes.T @ offsets.T).T, 0, 1)
    np.testing.assert_allclose(
        np.asarray(_solve_all(problem, targets, inverse.Joshi()).weights), joshi, atol=2e-3
    )
    np.testing.assert_allclose(
        np.asarray(_solve_all(problem, targets, inverse.Cetinaslan(alpha=alpha)).weights),
        cetinaslan,
        atol=2e-3,
    )


def test_bad_input_raises_before_tracing(setup):
    rig, problem, _, targets = setup
    method = inverse.QuarticCD()
    with pytest.raises(ValueError, match="target"):
        inverse.solve(problem, targets[0][:-1], method)
    with pytest.raises(ValueError, match="target"):
        inverse.solve(problem, np.asarray(targets[0]).copy() * np.nan, method)
    with pytest.raises(ValueError, match="alpha"):
        inverse.QuarticCD(alpha=-1.0)
    with pytest.raises(ValueError, match="passes"):
        inverse.QuarticCD(passes=0)
    with pytest.raises(ValueError, match="order"):
        inverse.solve(problem, targets[0], method, order="sideways")
    zero = type(rig)(rig.neutral, rig.deltas.at[3].set(0.0), (), rig.names, rig.faces)
    with pytest.raises(ValueError, match="zero norm"):
        inverse.prepare(zero)
