"""sigma: the GUI mapping, the closed-form leave-one-out error, the optimistix fit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.wpse import (
    GUI_MIN,
    fit_sigma,
    gui_from_sigma,
    loo_error,
    loo_residuals,
    prepare_edits,
    sigma_from_gui,
)
from canrig_jax.wpse.reference import reference_coefficients


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


def test_fit_sigma_finds_the_loo_minimum(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    data = prepare_edits(tiny_rig, poses, edits)
    fit = fit_sigma(data)
    assert fit.sigma > 0 and np.isfinite(fit.loo_rms)
    assert fit.loo_rms <= fit.grid_rms.min() + 1e-6
    dense = np.geomspace(fit.grid[0], fit.grid[-1], 100)
    loss = jax.jit(jax.vmap(lambda s: loo_error(data.metric, data.poses, data.displacements, s)))
    losses = np.asarray(loss(jnp.asarray(dense, jnp.float32)))
    assert fit.loo_rms**2 <= min(losses) * (1 + 1e-3) + 1e-12


def test_fit_sigma_bad_input(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    one = prepare_edits(tiny_rig, poses[:1], edits[:1])
    with pytest.raises(ValueError, match="at least 2"):
        fit_sigma(one)
    data = prepare_edits(tiny_rig, poses, edits)
    with pytest.raises(ValueError, match="grid"):
        fit_sigma(data, grid=np.array([0.1, -1.0]))
