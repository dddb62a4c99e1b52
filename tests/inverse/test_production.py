"""The production solver's terms on ``inverse.Constrained`` (symmetry ties, L2, the temporal
term of a ``Stream``, an active-shape mask, per-shape multipliers and offsets), each against an
independent computation on the small synthetic rig (pair, triplet and quad correctives):

- every quadratic term is the data term of a larger rig: extra vertices whose deltas are the
  rows of the penalty's matrix and whose target is its constant, so the penalised solve must
  equal the plain ``QuarticNewton`` solve of that augmented rig, built here with ``evaluate``'s
  own rig class and nothing of ``Constrained``;
- with a large tie weight the tied solution is the solve of the symmetrised rig (each tied
  pair merged into one shape, its deltas summed);
- multipliers and offsets are exact on the solved weights; an inactive shape is exactly 0.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import inverse
from canrig_jax.rig import BlendshapeRig, Corrective, evaluate

BASE = inverse.QuarticNewton(alpha=0.05, iterations=60, tol=1e-7)
TIES = ((4, 5), (6, 7))


@pytest.fixture(scope="module")
def rig_and_take(synthetic_rig):
    """(rig, problem, (3, V, 3) noisy targets of random sparse poses)."""
    rig = synthetic_rig
    rng = np.random.default_rng(11)
    weights = rng.uniform(0, 1, (3, rig.n_blendshapes)).astype(np.float32)
    weights[weights < 0.3] = 0.0
    clean = np.asarray(jax.vmap(evaluate, (None, 0))(rig, weights))
    noisy = clean + rng.normal(0, np.sqrt(0.03), clean.shape)
    return rig, inverse.prepare(rig), noisy.astype(np.float32)


def _augmented(rig, rows, values):
    """``rig`` with one extra vertex per row of ``rows`` (R, K): shape i moves it by
    (rows[r, i], 0, 0), and the extra part of a target is (values[r], 0, 0), so the data term
    gains 1/2 ||rows w - values||^2. Returns (augmented rig, function target -> augmented)."""
    rows = np.asarray(rows, np.float32)
    extra = rows.shape[0]
    neutral = np.concatenate([np.asarray(rig.neutral), np.zeros((extra, 3), np.float32)])
    moves = np.zeros((rig.n_blendshapes, extra, 3), np.float32)
    moves[:, :, 0] = rows.T
    deltas = np.concatenate([np.asarray(rig.deltas), moves], axis=1)
    correctives = tuple(
        Corrective(c.indices, c.vertices, c.deltas) for c in rig.correctives
    )  # the same sparse correctives: they move none of the extra vertices
    bigger = BlendshapeRig(neutral, deltas, correctives, rig.names, rig.faces, units=rig.units)
    target_rows = np.zeros((extra, 3), np.float32)
    target_rows[:, 0] = values

    def target(mesh):
        return np.concatenate([np.asarray(mesh, np.float32), target_rows])

    return bigger, target


def _tie_rows(k, ties, weight):
    rows = np.zeros((len(ties), k))
    for r, (i, j) in enumerate(ties):
        rows[r, i], rows[r, j] = np.sqrt(weight), -np.sqrt(weight)
    return rows


@pytest.mark.slow
def test_ties_and_l2_are_the_solve_of_the_augmented_rig(rig_and_take):
    rig, problem, targets = rig_and_take
    k, tie, l2 = rig.n_blendshapes, 40.0, 3.0
    method = inverse.Constrained(BASE, ties=TIES, tie_weight=tie, l2_weight=l2)
    rows = np.concatenate([_tie_rows(k, TIES, tie), np.sqrt(l2) * np.eye(k)])
    bigger, target = _augmented(rig, rows, np.zeros(len(rows)))
    reference = inverse.prepare(bigger)
    for frame in targets[:2]:
        ours = inverse.solve(problem, frame, method)
        theirs = inverse.solve(reference, target(frame), BASE)
        np.testing.assert_allclose(np.asarray(ours.weights), np.asarray(theirs.weights), atol=2e-4)
        # the tie matters here: unpenalised, the pairs are further apart
    free = inverse.solve(problem, targets[0], BASE).weights
    tied = inverse.solve(problem, targets[0], method).weights
    gap = [abs(float(w[i] - w[j])) for w in (free, tied) for i, j in TIES]
    assert sum(gap[2:]) < 0.5 * sum(gap[:2])


@pytest.mark.slow
def test_the_temporal_term_of_a_stream_is_the_solve_of_the_augmented_rig(rig_and_take):
    """Frame 1 of a warm stream minimises data + L1 + temporal_weight / 2 ||w - w_0||^2 with
    w_0 frame 0's solved weights; frame 0 (no previous frame) is the plain solve."""
    rig, problem, targets = rig_and_take
    k, temporal = rig.n_blendshapes, 25.0
    method = inverse.Constrained(BASE, temporal_weight=temporal)
    stream = inverse.Stream(problem, method, warm_start=True)
    first = stream(targets[0])
    plain = inverse.solve(problem, targets[0], BASE)
    np.testing.assert_allclose(np.asarray(first.weights), np.asarray(plain.weights), atol=1e-6)
    second = stream(targets[1])
    previous = np.asarray(first.weights)
    bigger, target = _augmented(rig, np.sqrt(temporal) * np.eye(k), np.sqrt(temporal) * previous)
    reference = inverse.solve(inverse.prepare(bigger), target(targets[1]), BASE, init=previous)
    np.testing.assert_allclose(np.asarray(second.weights), np.asarray(reference.weights), atol=2e-4)
    # and it is not the per-frame solve: the term pulls frame 1 towards frame 0
    alone = np.asarray(inverse.solve(problem, targets[1], BASE).weights)
    moved = np.abs(np.asarray(second.weights) - previous).sum()
    assert moved < 0.8 * np.abs(alone - previous).sum()
    # without warm starts there is no previous frame: every frame is the plain solve
    cold = inverse.Stream(problem, method)
    cold(targets[0])
    np.testing.assert_allclose(np.asarray(cold(targets[1]).weights), alone, atol=1e-6)


def test_a_large_tie_is_the_solve_of_the_symmetrised_rig(synthetic_rig, rig_and_take):
    """Linear rig, no L1: with tie_weight large the tied pairs share one weight, and the
    solution is the solve of the rig whose tied pairs are merged into one shape."""
    _, _, targets = rig_and_take
    linear = BlendshapeRig(synthetic_rig.neutral, synthetic_rig.deltas, (), synthetic_rig.names)
    base = inverse.QuarticNewton(alpha=0.0, iterations=60, tol=1e-7, upper=jnp.inf)
    tied = inverse.Constrained(base, ties=TIES, tie_weight=1e4)
    ours = np.asarray(inverse.solve(inverse.prepare(linear), targets[0], tied).weights)
    deltas = np.asarray(linear.deltas)
    keep = [0, 1, 2, 3]
    merged = np.concatenate([deltas[keep], [deltas[i] + deltas[j] for i, j in TIES]])
    symmetric = BlendshapeRig(linear.neutral, merged)
    theirs = np.asarray(inverse.solve(inverse.prepare(symmetric), targets[0], base).weights)
    expected = np.concatenate([theirs[:4], np.repeat(theirs[4:], 2)])
    np.testing.assert_allclose(ours, expected, atol=3e-3)


@pytest.mark.slow
def test_multipliers_and_offsets_are_exact_and_clipped(rig_and_take):
    rig, problem, targets = rig_and_take
    k = rig.n_blendshapes
    multipliers = np.linspace(0.5, 2.5, k).astype(np.float32)
    offsets = np.linspace(-0.2, 0.3, k).astype(np.float32)
    exclusive = ((0, 1),)
    plain = inverse.Constrained(BASE, exclusive=exclusive)
    scaled = inverse.Constrained(
        BASE, exclusive=exclusive, multipliers=multipliers, offsets=offsets
    )
    raw = np.asarray(inverse.solve_sequence(problem, targets, plain).weights)
    out = np.asarray(inverse.solve_sequence(problem, targets, scaled).weights)
    expected = np.clip(multipliers * raw + offsets, 0.0, 1.0)
    for e in expected:  # the exclusive pair stays exclusive: the smaller member goes to 0
        if e[0] > 0 and e[1] > 0:
            e[np.argmin(e[:2])] = 0.0
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)
    assert out.max() <= 1.0 and out.min() >= 0.0 and (expected == 1.0).any()
    # one number applies to every shape
    uniform = inverse.Constrained(BASE, multipliers=2.0, offsets=0.1)
    np.testing.assert_allclose(
        np.asarray(inverse.solve(problem, targets[0], uniform).weights),
        np.clip(2.0 * np.asarray(inverse.solve(problem, targets[0], BASE).weights) + 0.1, 0, 1),
        rtol=1e-6,
        atol=1e-7,
    )


def test_inactive_shapes_are_exactly_zero_without_recompiling(rig_and_take):
    rig, problem, targets = rig_and_take
    k = rig.n_blendshapes
    traces = []

    @jax.jit
    def solve(mask, target):
        traces.append(1)
        method = inverse.Constrained(BASE, active=mask, offsets=0.2)
        return inverse.solve(problem, target, method).weights

    for off in ([2, 5], [0, 1, 7]):
        mask = np.ones(k, bool)
        mask[off] = False
        weights = np.asarray(solve(jnp.asarray(mask), targets[0]))
        assert np.all(weights[off] == 0.0)  # exactly, despite the offset of 0.2
        # the others: the solve with those shapes' bounds at 0 (an independent route), + 0.2
        upper = mask.astype(np.float32)
        held = inverse.QuarticNewton(alpha=BASE.alpha, iterations=60, tol=1e-7, upper=upper)
        reference = np.asarray(inverse.solve(problem, targets[0], held).weights)
        np.testing.assert_allclose(
            weights, np.clip(reference + 0.2, 0, 1) * mask, rtol=1e-5, atol=1e-5
        )
    assert len(traces) == 1  # the second mask reused the compiled solve


@pytest.mark.slow
def test_the_terms_compose_under_vmap(rig_and_take):
    rig, problem, targets = rig_and_take
    method = inverse.Constrained(
        BASE, exclusive=((0, 1),), ties=TIES, tie_weight=5.0, l2_weight=0.5,
        active=np.arange(rig.n_blendshapes) != 3, multipliers=1.5, offsets=0.05,
    )  # fmt: skip
    batch = inverse.solve_sequence(problem, targets, method)
    for t in range(targets.shape[0]):
        single = inverse.solve(problem, targets[t], method)
        np.testing.assert_allclose(
            np.asarray(single.weights), np.asarray(batch.weights[t]), atol=1e-4
        )
    assert np.all(np.asarray(batch.weights)[:, 3] == 0.0)


@pytest.mark.bad_input
def test_bad_input_is_named_before_compiling(rig_and_take):
    rig, problem, _ = rig_and_take
    k = rig.n_blendshapes
    with pytest.raises(ValueError, match=r"ties: names not in the rig: \['eyeBlinkLeft'\]"):
        inverse.pair_indices(rig.names, (("shape4", "eyeBlinkLeft"),), argument="ties")
    with pytest.raises(ValueError, match="pairs"):
        inverse.pair_indices(rig.names, (("shape4",),))
    assert inverse.pair_indices(rig.names, (("shape4", "shape5"),)) == ((4, 5),)
    # a Stream compiles nothing at construction: these are raised in plain Python
    for field, value in (
        ("multipliers", np.ones(k - 1)),
        ("offsets", np.zeros(k + 2)),
        ("active", np.ones(k + 1, bool)),
    ):
        with pytest.raises(ValueError, match=f"{field}: expected \\({k},\\)"):
            inverse.Stream(problem, inverse.Constrained(BASE, **{field: value}))
        with pytest.raises(ValueError, match=field):
            inverse.solve(
                problem, np.asarray(problem.neutral), inverse.Constrained(BASE, **{field: value})
            )
    with pytest.raises(ValueError, match="ties"):
        inverse.Stream(problem, inverse.Constrained(BASE, ties=((0, k),)))
    for field, value in (
        ("multipliers", [1.0, np.nan]),
        ("active", [0.5, 1.0]),
        ("active", 1.0),
        ("temporal_weight", -1.0),
        ("l2_weight", np.inf),
    ):
        with pytest.raises(ValueError, match=field):
            inverse.Constrained(BASE, **{field: value})
