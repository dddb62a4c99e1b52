"""sigma: the GUI mapping, the closed-form leave-one-out error, the optimistix fit."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.papers.wpse import reference_coefficients
from canrig_jax.wpse import fit_sigma, prepare_edits, sigma_from_gui
from canrig_jax.wpse._sigma import GUI_MIN, gui_from_sigma, loo_residuals


def test_gui_mapping_fixed_points_and_monotone():
    assert sigma_from_gui(0.01) == pytest.approx(0.01, abs=1e-12)
    assert sigma_from_gui(0.99) == pytest.approx(0.99, abs=1e-12)
    values = [sigma_from_gui(g) for g in np.linspace(0.001, 0.999, 50)]
    assert np.all(np.diff(values) > 0)
    # the paper's form, with lambda and c solved from the two fixed points
    lam = 0.98 / (np.sqrt(-1 / np.log(0.99)) - np.sqrt(-1 / np.log(0.01)))
    c = 0.01 - lam * np.sqrt(-1 / np.log(0.01))
    assert sigma_from_gui(0.5) == pytest.approx(lam * np.sqrt(-1 / np.log(0.5)) + c)
    for g in (0.001, 0.3, 0.9):
        assert gui_from_sigma(sigma_from_gui(g)) == pytest.approx(g, rel=1e-9)


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.5, 1.5, np.nan, GUI_MIN / 2])
def test_gui_mapping_rejects_out_of_range(bad):
    with pytest.raises(ValueError, match="sigma_g"):
        sigma_from_gui(bad)


def test_gui_inverse_rejects_nonpositive_sigma():
    with pytest.raises(ValueError, match="sigma"):
        gui_from_sigma(0.0)


def test_loo_residuals_match_explicit_refits():
    """Rippa's X_i / (Phi^-1)_ii equals refitting without edit i and predicting it."""
    rng = np.random.default_rng(0)
    s, p, k, sigma = 3, 6, 4, 0.6
    metric = rng.uniform(0.1, 1, (s, k))
    poses = rng.uniform(0, 1, (p, k))
    d = rng.normal(size=(s, p, 3))
    got = np.asarray(loo_residuals(metric, poses, d, sigma, ridge=0.0))
    for i in range(p):
        keep = np.arange(p) != i
        x = reference_coefficients(metric, poses[keep], d[:, keep], sigma)
        r2 = np.einsum("sk,pk->sp", metric, (poses[i] - poses[keep]) ** 2)
        predicted = np.einsum("sp,spc->sc", np.exp(-r2 / (2 * sigma**2)), x)
        np.testing.assert_allclose(got[:, i], d[:, i] - predicted, rtol=2e-3, atol=2e-4)


def _numpy_loo_rms(metric, poses, displacements, sigma, ridge):
    """Leave-one-out RMS error by explicit refits in float64 NumPy (no Rippa shortcut):
    refit without edit i, predict edit i, over every edit and vertex."""
    metric, poses = np.asarray(metric, np.float64), np.asarray(poses, np.float64)
    d = np.asarray(displacements, np.float64)
    errors = []
    for i in range(poses.shape[0]):
        keep = np.arange(poses.shape[0]) != i
        x = reference_coefficients(metric, poses[keep], d[:, keep], sigma, ridge)
        r2 = np.einsum("sk,pk->sp", metric, (poses[i] - poses[keep]) ** 2)
        predicted = np.einsum("sp,spc->sc", np.exp(-r2 / (2 * sigma**2)), x)
        errors.append(np.sum((d[:, i] - predicted) ** 2, axis=-1))
    return float(np.sqrt(np.mean(errors)))


@pytest.mark.parametrize("metric", ["weighted", "euclidean"])
def test_fit_sigma_finds_the_loo_minimum(tiny_rig, metric):
    """BFGS's sigma is the minimiser of the LOO error computed independently (explicit NumPy
    refits, bounded scalar minimisation over log sigma), not merely the best grid point.
    The edits are a smooth function of the pose (squared weights through the rig's deltas),
    so the LOO curve has an interior minimum (random edits would put it at sigma -> 0)."""
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(3)
    poses = rng.uniform(0, 1, (9, tiny_rig.n_blendshapes)).astype(np.float32)
    edits = 0.5 * np.tensordot(np.sin(2.0 * poses) ** 2, np.asarray(tiny_rig.deltas), 1)
    data = prepare_edits(tiny_rig, poses, edits.astype(np.float32), metric=metric)
    fit = fit_sigma(data)
    assert fit.successful  # BFGS converged: the grid fallback did not decide the answer
    assert not np.any(np.isclose(fit.sigma, fit.grid, rtol=1e-4))  # refined off the grid

    args = (data.metric, data.poses, data.displacements)
    dense = np.geomspace(fit.grid[0], fit.grid[-1], 60)
    curve = [_numpy_loo_rms(*args, s, 1e-6) for s in dense]
    best = int(np.argmin(curve))
    lo, hi = np.log(dense[max(best - 1, 0)]), np.log(dense[min(best + 1, len(dense) - 1)])
    independent = minimize_scalar(
        lambda t: _numpy_loo_rms(*args, np.exp(t), 1e-6),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-5},
    )
    sigma_star, rms_star = float(np.exp(independent.x)), float(independent.fun)
    assert fit.sigma == pytest.approx(sigma_star, rel=0.05)
    assert fit.loo_rms == pytest.approx(rms_star, rel=1e-3)
    assert _numpy_loo_rms(*args, fit.sigma, 1e-6) <= rms_star * (1 + 1e-3)


def test_fit_sigma_bad_input(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    one = prepare_edits(tiny_rig, poses[:1], edits[:1])
    with pytest.raises(ValueError, match="at least 2"):
        fit_sigma(one)
    data = prepare_edits(tiny_rig, poses, edits)
    with pytest.raises(ValueError, match="grid"):
        fit_sigma(data, grid=np.array([0.1, -1.0]))
