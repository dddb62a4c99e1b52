"""``inverse.retarget``: a take carried onto another control set of one mesh, checked against
closed forms (permuted and scaled controls), SciPy's bounded least squares, and the rig's own
evaluation; clear errors before any compiled work. The real Rocketbox heads are ``-m slow``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from canrig_jax import inverse
from canrig_jax.data import data_file, load_livelinkface
from canrig_jax.rig import (
    BlendshapeRig,
    evaluate_batch,
    load_fbx_rig,
    select_control_set,
)

NEWTON = inverse.QuarticNewton(alpha=0.0, tol=0.0, iterations=30)
"""Run to its iteration cap: the tests compare minima, not stopping rules."""


@pytest.fixture(scope="module")
def weights():
    """(6, 8) source weights in [0, 1], a few of them 0."""
    rng = np.random.default_rng(11)
    w = rng.uniform(0.0, 1.0, size=(6, 8)).astype(np.float32)
    w[rng.uniform(size=w.shape) < 0.25] = 0.0
    return w


def _rig(rig: BlendshapeRig, deltas, names, correctives=(), units=None, scale=1.0):
    return BlendshapeRig(
        np.asarray(rig.neutral) * scale,
        np.asarray(deltas) * scale,
        correctives,
        names,
        rig.faces,
        units or rig.units,
    )


def test_permuted_and_scaled_controls_give_the_closed_form_weights(synthetic_rig, weights):
    source = synthetic_rig.linear()
    order = np.array([3, 0, 7, 5, 1, 6, 2, 4])
    scale = np.linspace(1.0, 2.0, 8).astype(np.float32)
    deltas = np.asarray(source.deltas)[order] * scale[:, None, None]
    target = _rig(source, deltas, source.names)  # same names: one compiled solve for the file
    solution = inverse.retarget(source, weights, target, NEWTON)
    # f_target(w') = f_source(w) exactly when w'_j s_j = w_p(j)
    np.testing.assert_allclose(solution.weights, weights[:, order] / scale, atol=2e-4)
    assert solution.weights.shape == (6, 8) and solution.objective.shape == (6,)


def test_matches_bounded_least_squares_when_the_target_cannot_show_the_source(
    synthetic_rig, weights
):
    # the source has correctives, the target is its linear part: the answer is the
    # box-constrained least-squares fit of each frame's offsets
    target = synthetic_rig.linear()
    solution = inverse.retarget(synthetic_rig, weights, target, NEWTON)
    offsets = np.asarray(evaluate_batch(synthetic_rig, weights) - synthetic_rig.neutral)
    basis = np.asarray(target.deltas, np.float64).reshape(target.n_blendshapes, -1).T
    for t, offset in enumerate(offsets):
        expected = lsq_linear(basis, offset.ravel(), bounds=(0.0, 1.0), tol=1e-12).x
        np.testing.assert_allclose(solution.weights[t], expected, atol=2e-3)


def test_units_of_the_target_rig_are_converted(synthetic_rig, weights):
    source = synthetic_rig.linear()
    # the same rig in mm drives the one in cm with the same weights (offsets scaled by 1/10)
    in_mm = _rig(source, source.deltas, source.names, units="mm", scale=10.0)
    solution = inverse.retarget(in_mm, weights, source, NEWTON)
    np.testing.assert_allclose(solution.weights, weights, atol=2e-4)
    # read as cm, the mm rig's neutral lies 10x away: not the same mesh
    as_cm = _rig(in_mm, in_mm.deltas, in_mm.names, units="cm")
    with pytest.raises(ValueError, match="target_rig: its neutral lies"):
        inverse.retarget(as_cm, weights, source, NEWTON)


def test_correctives_false_inverts_on_the_linear_part(synthetic_rig, weights):
    # the source is the linear part, so only the linear part of the target shows it exactly
    # (with the correctives, the best fit differs from the source's weights)
    source = synthetic_rig.linear()
    linear = inverse.retarget(source, weights, synthetic_rig, NEWTON, correctives=False)
    np.testing.assert_allclose(linear.weights, weights, atol=2e-4)


def test_a_zero_target_shape_gets_a_zero_curve_with_a_warning(synthetic_rig, weights):
    source = synthetic_rig.linear()
    deltas = np.concatenate([np.asarray(source.deltas), np.zeros_like(source.deltas[:1])])
    target = _rig(source, deltas, [*source.names, "blank"])
    with pytest.warns(UserWarning, match=r"\['blank'\].*all-zero"):
        solution = inverse.retarget(source, weights, target, NEWTON)
    assert np.all(np.asarray(solution.weights)[:, -1] == 0.0)
    np.testing.assert_allclose(solution.weights[:, :-1], weights, atol=2e-4)


def test_rigs_on_different_meshes_are_refused(synthetic_rig, weights):
    source = synthetic_rig.linear()
    fewer = BlendshapeRig(source.neutral[:-1], source.deltas[:, :-1], (), source.names)
    with pytest.raises(ValueError, match=r"target_rig: has 399 vertices, source_rig 400"):
        inverse.retarget(source, weights, fewer, NEWTON)
    neutral = np.asarray(source.neutral).copy()
    neutral[17, 2] += 0.05
    moved = BlendshapeRig(neutral, source.deltas, (), source.names, source.faces, source.units)
    with pytest.raises(ValueError, match=r"target_rig: its neutral lies 0.5 mm .* vertex 17"):
        inverse.retarget(source, weights, moved, NEWTON)
    # within a looser tolerance it is the same mesh
    inverse.retarget(source, weights, moved, NEWTON, neutral_tol_mm=1.0)


def test_bad_weights_are_named(synthetic_rig, weights):
    source = synthetic_rig.linear()
    with pytest.raises(ValueError, match=r"weights: expected shape \(T, 8\)"):
        inverse.retarget(source, weights[:, :5], source, NEWTON)
    with pytest.raises(ValueError, match=r"weights: expected shape \(T, 8\)"):
        inverse.retarget(source, weights[:0], source, NEWTON)
    bad = weights.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"weights: frames \[4\]"):
        inverse.retarget(source, bad, source, NEWTON)
    with pytest.raises(ValueError, match="neutral_tol_mm"):
        inverse.retarget(source, weights, source, NEWTON, neutral_tol_mm=-1.0)


@pytest.mark.bad_input
def test_inputs_outside_the_annotations_are_named(synthetic_rig, weights):
    source = synthetic_rig.linear()
    with pytest.raises(TypeError, match="method: expected an inverse-rig method"):
        inverse.retarget(source, weights, source, "newton")
    with pytest.raises(TypeError, match="target_rig: expected a BlendshapeRig"):
        inverse.retarget(source, weights, inverse.prepare(source), NEWTON)
    with pytest.raises(ValueError, match="weights: expected shape"):
        inverse.retarget(source, weights[0], source, NEWTON)
    with pytest.raises(TypeError, match="warm_start: expected a bool"):
        inverse.retarget(source, weights, source, NEWTON, warm_start=1)


@pytest.mark.slow  # ~15 s: the real Rocketbox head, all 175 shapes, three control sets
def test_rocketbox_capture_round_trips_and_reaches_the_other_sets(data_dir):
    rig = load_fbx_rig(data_file("rocketbox/Female_Adult_01_facial.fbx", data_dir), names="all",
                       crop="head")  # fmt: skip
    arkit = select_control_set(rig, "arkit")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the take's dropped frames
        weights = load_livelinkface(data_dir).weights_for(arkit.names)
    source = np.asarray(evaluate_batch(arkit, weights) - arkit.neutral)
    same = inverse.retarget(arkit, weights, arkit, inverse.QuarticNewton())
    fitted = np.asarray(evaluate_batch(arkit, same.weights) - arkit.neutral)
    rmse_mm = np.sqrt((np.linalg.norm(fitted - source, axis=-1) ** 2).mean(axis=1)) * 10
    assert rmse_mm.max() < 0.1  # the source's own controls show it (to float32 precision)
    for name in ("sranipal", "facs"):
        target = select_control_set(rig, name)
        solution = inverse.retarget(arkit, weights, target, inverse.QuarticNewton())
        got = np.asarray(solution.weights)
        assert np.all(np.isfinite(got)) and got.min() >= 0.0 and got.max() <= 1.0
        shown = np.asarray(evaluate_batch(target, got) - target.neutral)
        error = np.sqrt((np.linalg.norm(shown - source, axis=-1) ** 2).mean(axis=1))
        still = np.sqrt((np.linalg.norm(source, axis=-1) ** 2).mean(axis=1))
        # the other set shows most of the motion: far closer than the neutral face
        assert np.mean(error) < 0.5 * np.mean(still)
