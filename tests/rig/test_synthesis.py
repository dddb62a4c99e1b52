"""Corrective synthesis against the deformation-gradient blend it sculpts from: exact corners,
inclusion-exclusion, thresholds and exclusions, on a real ICT sub-rig and the ict-quartic rig."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from canrig_jax.mesh import DeformationGradientBlend
from canrig_jax.rig import (
    MUTUALLY_EXCLUSIVE,
    BlendshapeRig,
    SynthesisOptions,
    evaluate_batch,
    synthesize_correctives,
)

SUB_SHAPES = (
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthSmile_L",
    "eyeBlink_L",
    "browDown_L",
    "jawLeft",
    "jawRight",
)
# Thresholds that keep some and drop some candidates of every order on this sub-rig: the pair
# and triplet thresholds fall between observed magnitudes (margins >= 0.002 cm), and the
# triplet jawOpen/mouthFunnel/mouthPucker (~0.42 cm) is dropped though its quad is kept, so
# the quad must absorb its remainder.
SUB_OPTIONS = SynthesisOptions(max_order=4, min_magnitude=(0.075, 0.45, 0.05))

_batch = evaluate_batch


def _corners(combos, k: int) -> np.ndarray:
    out = np.zeros((len(combos), k))
    for row, combo in enumerate(combos):
        out[row, list(combo)] = 1.0
    return out


def _max_norm(offsets: np.ndarray) -> np.ndarray:
    """Largest per-vertex offset of each (..., V, 3) array."""
    return np.linalg.norm(offsets, axis=-1).max(axis=-1)


def _kept(rig: BlendshapeRig, order: int) -> dict[tuple[int, ...], np.ndarray]:
    """{sorted index tuple: dense (V, 3) corrective} of one order."""
    table = rig.corrective(order)
    if table is None:
        return {}
    dense = table.to_dense(rig.n_vertices)
    return {
        tuple(sorted(c)): d for c, d in zip(np.asarray(table.indices).tolist(), dense, strict=True)
    }


@pytest.fixture(scope="module")
def sub_linear(ict_face):
    index = ict_face.index(SUB_SHAPES)
    return BlendshapeRig(ict_face.neutral, ict_face.deltas[index], (), SUB_SHAPES, ict_face.faces)


@pytest.fixture(scope="module")
def sub_blend(sub_linear):
    return DeformationGradientBlend(
        np.asarray(sub_linear.neutral), np.asarray(sub_linear.deltas), np.asarray(sub_linear.faces)
    )


@pytest.fixture(scope="module")
def sub_synthesis(sub_linear, sub_blend):
    return synthesize_correctives(sub_linear, SUB_OPTIONS, blend=sub_blend, progress=False)


@pytest.fixture(scope="module")
def sub_candidates(sub_linear, sub_synthesis):
    """Candidate combinations per order, recomputed here from the options' definitions:
    pairs whose supports share >= min_overlap vertices, minus exclusions; triplets and quads
    all of whose pairs carry a corrective above combine_min_magnitude."""
    rig, _ = sub_synthesis
    deltas = np.asarray(sub_linear.deltas)
    support = np.linalg.norm(deltas, axis=2) > SUB_OPTIONS.support_tol
    excluded = {frozenset(p) for p in SUB_OPTIONS.exclude}
    k = len(SUB_SHAPES)
    pairs = [
        (i, j)
        for i, j in itertools.combinations(range(k), 2)
        if (support[i] & support[j]).sum() >= SUB_OPTIONS.min_overlap
        and frozenset((SUB_SHAPES[i], SUB_SHAPES[j])) not in excluded
    ]
    combine = SUB_OPTIONS.combine_min_magnitude
    strong = {p for p, d in _kept(rig, 2).items() if _max_norm(d) > combine}
    higher = {
        n: [
            c
            for c in itertools.combinations(range(k), n)
            if all(p in strong for p in itertools.combinations(c, 2))
        ]
        for n in (3, 4)
    }
    return {2: pairs, **higher}


def test_sub_rig_exercises_every_order(sub_synthesis):
    """Guard on the fixture: this sub-rig keeps and drops combinations of several orders."""
    rig, report = sub_synthesis
    assert [c.order for c in rig.correctives] == [2, 3, 4]
    assert report.kept[2] >= 10 and report.kept[3] >= 3 and report.kept[4] >= 1
    assert report.candidates[2] > report.kept[2] and report.candidates[3] > report.kept[3]
    for order in (2, 3, 4):
        assert report.kept[order] == rig.n_correctives(order)


def test_rig_equals_the_blend_at_every_selected_corner(sub_linear, sub_blend, sub_synthesis):
    """Singles and every kept pair, triplet and quad: the finished rig is the nonlinear blend
    there (< 1e-3 mm), and the report's corner error says so too."""
    rig, report = sub_synthesis
    k = len(SUB_SHAPES)
    combos = [(i,) for i in range(k)] + [c for n in (2, 3, 4) for c in _kept(rig, n)]
    corners = _corners(combos, k)
    blended = sub_blend(corners)
    error = _max_norm(np.asarray(_batch(rig, corners), np.float64) - blended)
    assert error.max() < 1e-4
    assert report.corner_max_error < 1e-4
    np.testing.assert_allclose(report.corner_max_error, error.max(), atol=1e-5)
    # ... and the correctives were needed: the linear rig misses those corners by millimetres.
    linear = _max_norm(np.asarray(_batch(sub_linear, corners), np.float64) - blended)
    assert linear.max() > 0.5


def test_triplets_follow_inclusion_exclusion(sub_blend, sub_synthesis):
    """Every kept triplet had all of its pairs kept, so its corrective is exactly
    c_S = sum_{T subset S} (-1)^{|S|-|T|} N(1_T) with N the blend."""
    rig, _ = sub_synthesis
    pairs, triplets = _kept(rig, 2), _kept(rig, 3)
    assert triplets
    k = len(SUB_SHAPES)
    blend_at = _blends_at_sub_corners(sub_blend, triplets, k)
    for combo, corrective in triplets.items():
        assert all(p in pairs for p in itertools.combinations(combo, 2))
        subsets = [t for n in range(4) for t in itertools.combinations(combo, n)]
        blends = np.stack([blend_at[t] for t in subsets])
        signs = np.array([(-1) ** (3 - len(t)) for t in subsets], np.float64)
        expected = np.tensordot(signs, blends, axes=1)
        assert _max_norm(corrective - expected) < 1e-4, combo


def _blends_at_sub_corners(blend, combos, k: int) -> dict[tuple[int, ...], np.ndarray]:
    """{T: N(1_T)} for every subset T of every combination, in one call of the blend."""
    subsets = sorted(
        {t for c in combos for n in range(len(c) + 1) for t in itertools.combinations(c, n)}
    )
    return dict(zip(subsets, blend(_corners(subsets, k)), strict=True))


def _inclusion_exclusion(combo, blends) -> np.ndarray:
    """sum_{T subset combo} (-1)^{|combo|-|T|} N(1_T) from {T: N(1_T)}."""
    return sum(
        (-1) ** (len(combo) - n) * blends[t]
        for n in range(len(combo) + 1)
        for t in itertools.combinations(combo, n)
    )


def test_quad_absorbs_the_remainder_of_a_dropped_triplet(sub_blend, sub_synthesis):
    """When a sub-triplet was dropped for being small, the quad is no longer the pure
    inclusion-exclusion sum: it differs from it by exactly that triplet's (dropped) term."""
    rig, _ = sub_synthesis
    triplets, quads = _kept(rig, 3), _kept(rig, 4)
    k = len(SUB_SHAPES)
    absorbed = 0
    blend_at = _blends_at_sub_corners(sub_blend, quads, k)
    for combo, corrective in quads.items():
        subsets = [t for n in range(5) for t in itertools.combinations(combo, n)]
        blends = {t: blend_at[t] for t in subsets}
        mobius = lambda s, blends=blends: _inclusion_exclusion(s, blends)
        dropped = [t for t in itertools.combinations(combo, 3) if t not in triplets]
        expected = mobius(combo) + sum((mobius(t) for t in dropped), np.zeros_like(corrective))
        assert _max_norm(corrective - expected) < 1e-4
        if dropped:
            absorbed += 1
            assert _max_norm(corrective - mobius(combo)) > 0.05
    assert absorbed >= 1  # the options above make this case occur


def test_candidates_are_recomputed_independently(sub_synthesis, sub_candidates):
    rig, report = sub_synthesis
    for order in (2, 3, 4):
        assert report.candidates[order] == len(sub_candidates[order]), order
        assert set(_kept(rig, order)) <= set(sub_candidates[order]), order


def test_thresholds_are_respected(sub_linear, sub_blend, sub_synthesis, sub_candidates):
    """Every kept corrective is larger than its order's min_magnitude; every dropped
    candidate's residual N(1_S) - f(1_S) on the finished rig is at most that threshold."""
    rig, report = sub_synthesis
    k = len(SUB_SHAPES)
    for order in (2, 3, 4):
        threshold = SUB_OPTIONS.min_magnitude[order - 2]
        kept = _kept(rig, order)
        sizes = [_max_norm(d) for d in kept.values()]
        assert all(s > threshold for s in sizes), order
        assert report.max_magnitude[order] == pytest.approx(max(sizes, default=0.0), abs=1e-6)
        dropped = [c for c in sub_candidates[order] if c not in kept]
        if dropped:
            corners = _corners(dropped, k)
            residual = sub_blend(corners) - np.asarray(_batch(rig, corners), np.float64)
            assert np.all(_max_norm(residual) <= threshold + 1e-6), order
    assert report.fallback_triangles == sub_blend.fallback_counts.total


def test_mutually_exclusive_pairs_never_combine(sub_synthesis, ict_quartic):
    for rig in (sub_synthesis[0], ict_quartic):
        index = {n: i for i, n in enumerate(rig.names)}
        exclusive = [
            {index[a], index[b]} for a, b in MUTUALLY_EXCLUSIVE if a in index and b in index
        ]
        assert exclusive
        for table in rig.correctives:
            for combo in np.asarray(table.indices).tolist():
                assert not any(pair <= set(combo) for pair in exclusive), combo


@pytest.mark.slow
def test_custom_exclusion_removes_the_pair_and_everything_above_it(sub_linear, sub_blend):
    options = dataclasses.replace(SUB_OPTIONS, max_order=3, exclude=(("jawOpen", "mouthClose"),))
    rig, report = synthesize_correctives(sub_linear, options, blend=sub_blend, progress=False)
    i, j = sub_linear.index(["jawOpen", "mouthClose"])
    for table in rig.correctives:
        assert not any({i, j} <= set(c) for c in np.asarray(table.indices).tolist())
    # jawLeft/jawRight are no longer excluded, so they now pair up (they overlap on the jaw).
    left, right = sub_linear.index(["jawLeft", "jawRight"])
    assert (left, right) in _kept(rig, 2)


def test_existing_correctives_are_ignored(sub_synthesis, sub_blend):
    """Synthesising from a rig that already has correctives restarts from its linear part:
    the pair stage (which does not depend on max_order) gives the same pairs again."""
    rig, report = sub_synthesis
    options = dataclasses.replace(SUB_OPTIONS, max_order=2)
    again, report_again = synthesize_correctives(rig, options, blend=sub_blend, progress=False)
    assert report_again.kept == {2: report.kept[2]}
    first, second = rig.corrective(2), again.corrective(2)
    np.testing.assert_array_equal(first.indices, second.indices)
    np.testing.assert_allclose(
        first.to_dense(rig.n_vertices), second.to_dense(rig.n_vertices), atol=1e-6
    )


def test_max_order_one_adds_nothing(sub_linear, sub_blend):
    options = dataclasses.replace(SUB_OPTIONS, max_order=1)
    rig, report = synthesize_correctives(sub_linear, options, blend=sub_blend, progress=False)
    assert rig.correctives == () and report.kept == {}
    assert report.corner_max_error < 1e-4


# --- options ------------------------------------------------------------------------------------


@pytest.mark.bad_input
@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("max_order", 0),
        ("max_order", 5),
        ("min_magnitude", (0.05, 0.05)),
        ("min_magnitude", (0.05, -0.1, 0.05)),
        ("support_tol", 0.0),
        ("support_tol", -0.01),
        ("store_tol", -1e-5),
        ("min_overlap", 0),
        ("combine_min_magnitude", -0.1),
    ],
)
def test_bad_options_raise(field, value):
    with pytest.raises(ValueError, match=field):
        SynthesisOptions(**{field: value})


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("support_tol", math.nan),
        ("min_magnitude", (math.nan, 0.05, 0.05)),
        ("combine_min_magnitude", math.nan),
        ("store_tol", math.nan),
    ],
)
def test_non_finite_options_raise(field, value):
    """NaN compares False with everything, so it must be rejected explicitly (a NaN
    min_magnitude would otherwise silently keep no corrective)."""
    with pytest.raises(ValueError, match=field):
        SynthesisOptions(**{field: value})


def test_rig_without_faces_raises(sub_linear):
    with pytest.raises(ValueError, match="rig"):
        synthesize_correctives(BlendshapeRig(sub_linear.neutral, sub_linear.deltas), progress=False)


# --- the standard ict-quartic rig ----------------------------------------------------------------


def test_ict_quartic_counts(ict_quartic, ict_quartic_report):
    """Hundreds of pairs, dozens of triplets and quads, matching the stored tables."""
    report = ict_quartic_report
    assert 100 <= report.kept[2] < 1000
    assert 10 <= report.kept[3] < 500 and 10 <= report.kept[4] < 500
    for order in (2, 3, 4):
        assert report.kept[order] == ict_quartic.n_correctives(order)
        assert report.kept[order] <= report.candidates[order]
    assert [c.order for c in ict_quartic.correctives] == [2, 3, 4]
    assert ict_quartic.n_blendshapes == 53 and ict_quartic.n_vertices == 9409


def test_ict_quartic_corners_against_an_independent_blend(
    ict_quartic, ict_quartic_report, ict_face_blend
):
    """report.corner_max_error < 1e-4 cm, and checked here: the rig equals the blend of all
    53 expressions at a sample of the kept pair, triplet and quad corners."""
    assert ict_quartic_report.corner_max_error < 1e-4
    k = ict_quartic.n_blendshapes
    combos = [c for n in (2, 3, 4) for c in list(_kept(ict_quartic, n))[:: 12 if n == 2 else 2]]
    corners = _corners(combos, k)
    rig = np.asarray(_batch(ict_quartic, corners), np.float64)
    assert _max_norm(rig - ict_face_blend(corners)).max() < 1e-4


def test_ict_quartic_thresholds(ict_quartic):
    defaults = SynthesisOptions()
    for table in ict_quartic.correctives:
        sizes = _max_norm(np.asarray(table.deltas))
        assert sizes.min() > defaults.min_magnitude[table.order - 2]


def test_ict_quartic_quads_follow_inclusion_exclusion(ict_quartic, ict_face_blend):
    """Quads all of whose sub-triplets (hence sub-pairs) were kept: c_S is the alternating sum
    of the blend over the 16 sub-corners."""
    triplets, quads = _kept(ict_quartic, 3), _kept(ict_quartic, 4)
    full = [q for q in quads if all(t in triplets for t in itertools.combinations(q, 3))][:2]
    assert full
    k = ict_quartic.n_blendshapes
    blend_at = _blends_at_sub_corners(ict_face_blend, full, k)
    for combo in full:
        subsets = [t for n in range(5) for t in itertools.combinations(combo, n)]
        signs = np.array([(-1) ** (4 - len(t)) for t in subsets], np.float64)
        expected = np.tensordot(signs, np.stack([blend_at[t] for t in subsets]), axes=1)
        assert _max_norm(quads[combo] - expected) < 1e-4, combo
