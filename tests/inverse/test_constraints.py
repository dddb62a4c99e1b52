"""Mutually exclusive pairs and left/right ties (``inverse.Constrained``) on the small synthetic
rig (pair, triplet and quad correctives), its shapes named as ARKit controls: the first four
are two exclusive pairs (jaw, mouth) and the last four two left/right pairs."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.rig import BlendshapeRig, evaluate, exclusive_pairs

NAMES = (
    "jawLeft",
    "jawRight",
    "mouthLeft",
    "mouthRight",
    "eyeBlink_L",  # ICT spelling
    "eyeBlink_R",
    "browDownLeft",
    "browDownRight",
)
ALPHA = 0.05
TIE_WEIGHT = 3000.0  # cm^2: large against the data term of these shapes


@pytest.fixture(scope="module")
def named(synthetic_rig):
    """(rig with ``NAMES``, prepared problem)."""
    r = synthetic_rig
    rig = BlendshapeRig(r.neutral, r.deltas, r.correctives, NAMES, r.faces, units=r.units)
    return rig, inverse.prepare(rig)


@pytest.fixture(scope="module")
def conflicting_take(named):
    """(clean, noisy) meshes of six frames that turn on both members of the exclusive pair
    (0, 1) (frames 0-2) or of both exclusive pairs (0, 1) and (2, 3) (frames 3-5), and the
    other shapes at random; noise of variance 0.03 cm^2."""
    rig, _ = named
    rng = np.random.default_rng(7)
    weights = rng.uniform(0.0, 1.0, (6, rig.n_blendshapes)).astype(np.float32)
    weights[:, :4] = rng.uniform(0.3, 0.6, (6, 4))
    weights[:3, 3] = 0.0
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(rig, weights))
    noisy = clean + rng.normal(0.0, np.sqrt(0.03), clean.shape)
    return clean, noisy.astype(np.float32)


def _both_on(weights, pairs):
    """(T, E) whether both members of each pair are non-zero, per frame."""
    weights = np.asarray(weights).reshape(-1, np.shape(weights)[-1])
    return np.array([[w[i] > 0 and w[j] > 0 for i, j in pairs] for w in weights])


def test_pairs_from_names():
    assert exclusive_pairs(NAMES) == [(0, 1), (2, 3)]  # the ARKit default list
    assert exclusive_pairs(NAMES, (("JawRight", "jawLeft"),)) == [(0, 1)]
    # ICT spellings; pairs the rig lacks a member of are left out
    ict = ("eyeLookIn_L", "eyeLookOut_L", "eyeLookIn_R", "eyeLookOut_R", "jawLeft", "mouthLeft")
    assert exclusive_pairs(ict) == [(0, 1), (2, 3)]
    # ties: same stem with Left/Right or _L/_R; the exclusive pairs are not tied by default
    assert inverse.left_right_pairs(NAMES) == ((4, 5), (6, 7))
    assert inverse.left_right_pairs(NAMES, exclude=()) == ((0, 1), (2, 3), (4, 5), (6, 7))
    # both_active: per frame and pair, both members above the threshold
    weights = np.array([[0.5, 0.002, 0.0, 0.3], [0.5, 0.0005, 0.2, 0.3]])
    np.testing.assert_array_equal(
        inverse.both_active(weights, ((0, 1), (2, 3))), [[True, False], [False, True]]
    )
    assert inverse.both_active(weights, ((0, 1),), tol=0.0).all()


def _constrained(rig, tie_weight=0.0, exclusive=True):
    """The one configuration the tests compile (tie_weight is traced, not static)."""
    base = inverse.QuarticNewton(alpha=ALPHA)
    pairs = tuple(exclusive_pairs(rig.names)) if exclusive else ()
    ties = inverse.left_right_pairs(rig.names)
    return inverse.Constrained(base, exclusive=pairs, ties=ties, tie_weight=tie_weight)


@pytest.mark.slow
def test_no_exclusive_pair_is_both_on_and_the_cost_is_the_best_held_choice(named, conflicting_take):
    """On a take built to turn both members on: unconstrained, pairs are both on; constrained,
    none is (one member exactly 0) on any frame, batched or one frame at a time; the objective
    is no lower than unconstrained, no lower than the best way of holding one member of each
    pair at 0 (brute force, per-weight upper bounds, solved from zero), and equal to it when
    one pair conflicts."""
    rig, problem = named
    _, noisy = conflicting_take
    method = _constrained(rig)
    pairs = method.exclusive
    assert pairs == ((0, 1), (2, 3))
    free = inverse.solve_sequence(problem, noisy, method.method)
    conflicts = _both_on(free.weights, pairs)
    assert conflicts[:, 0].all() and conflicts[3:].any()  # the take does provoke conflicts
    held = inverse.solve_sequence(problem, noisy, method)
    assert not _both_on(held.weights, pairs).any()
    assert np.all(np.asarray(held.weights) >= 0)
    objective = np.asarray(held.objective, np.float64)
    assert np.all(objective >= np.asarray(free.objective) * (1 - 1e-6))
    for t in range(noisy.shape[0]):
        if t in (0, 3):  # one frame at a time: the same guarantee (one compile)
            single = inverse.solve(problem, noisy[t], method)
            assert not _both_on(single.weights, pairs).any()
            np.testing.assert_allclose(float(single.objective), objective[t], rtol=1e-5)
        choices = {}
        for members in itertools.product(*pairs):
            upper = np.ones(rig.n_blendshapes, np.float32)
            upper[list(members)] = 0.0
            solution = inverse.solve(
                problem, noisy[t], inverse.QuarticNewton(alpha=ALPHA, upper=upper)
            )
            choices[members] = float(solution.objective)
        assert objective[t] >= min(choices.values()) * (1 - 1e-5)
        if conflicts[t].sum() == 1:
            # the better of holding either member of the conflicting pair (the other pair's
            # members are as the unconstrained solve left them: one of them at 0)
            np.testing.assert_allclose(objective[t], min(choices.values()), rtol=1e-5)
        # the reported objective is the data term + L1 through the full rig
        mesh = np.asarray(evaluate(rig, held.weights[t]), np.float64)
        data = 0.5 * ((mesh - noisy[t]) ** 2).sum()
        l1 = ALPHA * float(np.asarray(held.weights[t], np.float64).sum())
        np.testing.assert_allclose(objective[t], data + l1, rtol=2e-4)


@pytest.mark.slow
def test_warm_started_take_stays_exclusive(named, conflicting_take):
    rig, problem = named
    _, noisy = conflicting_take
    method = _constrained(rig)
    solution = inverse.solve_sequence(problem, noisy, method, warm_start=True)
    assert not _both_on(solution.weights, method.exclusive).any()


@pytest.mark.slow
def test_ties(named, conflicting_take):
    """tie_weight = 0 reproduces the unconstrained solution exactly; the tied problem's
    objective is the data term + L1 + the tie penalty (against ``evaluate``); a large tie
    weight makes the tied pairs nearly equal, and the tied solution has the lower tied
    objective."""
    rig, problem = named
    _, noisy = conflicting_take
    off = _constrained(rig, exclusive=False)
    ties = off.ties
    free = inverse.solve_sequence(problem, noisy, off.method)
    untied = inverse.solve_sequence(problem, noisy, off)
    np.testing.assert_array_equal(np.asarray(untied.weights), np.asarray(free.weights))
    np.testing.assert_array_equal(np.asarray(untied.objective), np.asarray(free.objective))

    tied = _constrained(rig, tie_weight=TIE_WEIGHT, exclusive=False)
    model = tied.tied(problem)
    left, right = np.asarray(ties).T
    weights = np.random.default_rng(2).uniform(0, 1, (3, rig.n_blendshapes)).astype(np.float32)
    for w, b in zip(weights, noisy, strict=False):
        offset = jnp.asarray((b - np.asarray(problem.neutral)).reshape(-1))
        value = model.objective(jnp.asarray(w), model.projection(offset), offset @ offset, ALPHA)
        mesh = np.asarray(evaluate(rig, w), np.float64)
        penalty = TIE_WEIGHT / 2 * ((w[left].astype(np.float64) - w[right]) ** 2).sum()
        expected = 0.5 * ((mesh - b) ** 2).sum() + ALPHA * w.sum() + penalty
        np.testing.assert_allclose(float(value), expected, rtol=1e-4)
        np.testing.assert_allclose(float(tied.tie_penalty(w)), penalty, rtol=1e-5)

    solution = inverse.solve_sequence(problem, noisy, tied)
    gap_free = np.abs(np.asarray(free.weights)[:, left] - np.asarray(free.weights)[:, right])
    gap = np.abs(np.asarray(solution.weights)[:, left] - np.asarray(solution.weights)[:, right])
    assert gap_free.max() > 0.05 and gap.max() < 0.01
    with_penalty = np.asarray(solution.objective) + np.asarray(tied.tie_penalty(solution.weights))
    free_with = np.asarray(free.objective) + np.asarray(tied.tie_penalty(free.weights))
    assert np.all(with_penalty <= free_with * (1 + 1e-6))
    # the reported objective leaves the penalty out: never below the unconstrained minimum
    assert np.all(np.asarray(solution.objective) >= np.asarray(free.objective) * (1 - 1e-6))


@pytest.mark.bad_input
def test_bad_input_names_the_argument(named):
    rig, problem = named
    base = inverse.QuarticNewton(alpha=ALPHA)
    with pytest.raises(ValueError, match="exclude"):
        exclusive_pairs(NAMES, (("jawLeft", "jawLeftt"),))
    with pytest.raises(ValueError, match="exclude"):
        exclusive_pairs(NAMES, (("jawLeft", "jawLeft"),))
    with pytest.raises(ValueError, match="exclude"):
        exclusive_pairs(NAMES, ("jawLeft",))
    with pytest.raises(ValueError, match="names"):
        exclusive_pairs("jawLeft")
    with pytest.raises(ValueError, match="names"):
        inverse.left_right_pairs(("jawLeft", "jawLeft"))
    with pytest.raises(ValueError, match="exclusive"):
        inverse.Constrained(base, exclusive=((1, 1),))
    with pytest.raises(ValueError, match="exclusive"):
        inverse.Constrained(base, exclusive=((0, -1),))
    with pytest.raises(ValueError, match="ties"):
        inverse.Constrained(base, ties=((2, 2),))
    with pytest.raises(ValueError, match="ties"):
        inverse.Constrained(base, exclusive=((0, 1),), ties=((1, 0),), tie_weight=1.0)
    with pytest.raises(ValueError, match="tie_weight"):
        inverse.Constrained(base, ties=((4, 5),), tie_weight=-1.0)
    with pytest.raises(ValueError, match="tie_weight"):
        inverse.Constrained(base, ties=((4, 5),), tie_weight=float("nan"))
    with pytest.raises(TypeError, match="method"):
        inverse.Constrained(inverse.QuarticCD(alpha=ALPHA), exclusive=((0, 1),))
    with pytest.raises(ValueError, match="exclusive"):  # at the call: the rig has 8 weights
        inverse.solve(problem, np.asarray(problem.neutral), inverse.Constrained(base, ((0, 8),)))
    with pytest.raises(ValueError, match="upper"):
        inverse.QuarticNewton(upper=-np.ones(rig.n_blendshapes))
