"""The fix-shape method (eq. (8)): corner sculpts triggered by weight products."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.rig import evaluate, evaluate_batch
from canrig_jax.wpse import coactivation_pairs, fix_shape_rig


def sculpt_of(rig):
    """A made-up nonlinear 'sculpt': the linear mesh plus a bump growing with w0 * w1 * w2^2."""

    def sculpt(weights):
        weights = np.asarray(weights)
        linear = np.asarray(evaluate_batch(rig, weights))
        bump = np.sin(np.asarray(rig.neutral))
        return linear + (weights[:, 0] * weights[:, 1] + weights[:, 2] ** 2)[:, None, None] * bump

    return sculpt


def test_fix_shapes_exact_at_corners_and_quadratic_along_the_diagonal(tiny_rig):
    sculpt = sculpt_of(tiny_rig)
    triggers = np.array([[0, 1], [1, 3]])
    fsm = fix_shape_rig(tiny_rig, triggers, sculpt)
    corners = np.zeros((2, tiny_rig.n_blendshapes), np.float32)
    np.put_along_axis(corners, triggers, 1.0, axis=1)
    for corner, desired in zip(corners, sculpt(corners), strict=True):
        np.testing.assert_allclose(evaluate(fsm, corner), desired, atol=1e-5)
    shape = sculpt(corners[:1])[0] - np.asarray(evaluate(tiny_rig, corners[0]))
    for t in (0.3, 1.5):  # eq. (8): the trigger is w0 * w1 = t^2
        w = corners[0] * t
        np.testing.assert_allclose(
            evaluate(fsm, w) - evaluate(tiny_rig, w), t * t * shape, atol=1e-5
        )


def test_coactivation_pairs_by_brute_force():
    rng = np.random.default_rng(0)
    animation = rng.uniform(0, 1, (30, 5)) * (rng.uniform(0, 1, (30, 5)) > 0.5)
    got = coactivation_pairs(animation, 4)
    scores = {
        (a, b): float(np.sum(animation[:, a] * animation[:, b]))
        for a in range(5)
        for b in range(a + 1, 5)
    }
    best = sorted(scores, key=lambda pair: -scores[pair])[:4]
    assert [tuple(p) for p in got.tolist()] == best


def test_coactivation_excludes_opposite_directions():
    animation = np.ones((3, 3))
    got = coactivation_pairs(animation, 3, ("jawLeft", "jawRight", "jawOpen"))
    assert [0, 1] not in got.tolist() and len(got) == 2


def test_coactivation_excludes_opposites_in_any_spelling(ict_face, data_dir):
    """ICT names (``eyeLookUp_L``), their ARKit spelling (``eyeLookUpLeft``) and the capture's
    Unreal names (``EyeLookUpLeft``) all exclude the six pairs of opposite directions."""
    from canrig_jax.data import load_livelinkface, to_arkit
    from canrig_jax.rig import MUTUALLY_EXCLUSIVE

    ict = list(ict_face.names)
    unreal = list(load_livelinkface(data_dir).names)
    for names, variant in ((ict, ict), (ict, [to_arkit(n) for n in ict]), (unreal, unreal)):
        k, canonical = len(names), [to_arkit(n) for n in names]
        banned = {
            tuple(sorted((canonical.index(to_arkit(a)), canonical.index(to_arkit(b)))))
            for a, b in MUTUALLY_EXCLUSIVE
        }
        assert len(banned) == 6
        expected = {(i, j) for i in range(k) for j in range(i + 1, k)} - banned
        got = coactivation_pairs(np.ones((2, k)), k * k, variant)  # every pair co-activates
        assert {tuple(p) for p in got.tolist()} == expected


def test_fix_shape_rig_keeps_the_rig_unit(tiny_rig):
    from canrig_jax.rig import BlendshapeRig

    dm = BlendshapeRig(tiny_rig.neutral, tiny_rig.deltas, (), tiny_rig.names, tiny_rig.faces,
                       units="dm")  # fmt: skip
    assert fix_shape_rig(dm, np.array([[0, 1]]), sculpt_of(dm)).units == "dm"


def test_bad_input(tiny_rig):
    sculpt = sculpt_of(tiny_rig)
    with pytest.raises(ValueError, match="triggers"):
        fix_shape_rig(tiny_rig, np.array([[0, 9]]), sculpt)
    with pytest.raises(ValueError, match="^triggers:.*repeat"):
        fix_shape_rig(tiny_rig, np.array([[1, 1]]), sculpt)
    with pytest.raises(ValueError, match="sculpt"):
        fix_shape_rig(tiny_rig, np.array([[0, 1]]), lambda w: np.zeros((1, 3, 3)))
    fsm = fix_shape_rig(tiny_rig, np.array([[0, 1]]), sculpt)
    with pytest.raises(ValueError, match="rig"):
        fix_shape_rig(fsm, np.array([[2, 3]]), sculpt)
    with pytest.raises(ValueError, match="n_pairs"):
        coactivation_pairs(np.ones((2, 3)), 0)
