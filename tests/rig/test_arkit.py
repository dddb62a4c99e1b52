"""``rename_to_arkit``: a rig under ARKit's channel names shows what the source rig shows with
each merged channel's weight on every half (exact at 0 and 1 where a corrective is driven by
both halves), names every channel as ARKit does, and leaves an ARKit rig as it is."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import ARKIT_NAMES, to_arkit
from canrig_jax.rig import (
    BlendshapeRig,
    Corrective,
    arkit_channels,
    evaluate,
    evaluate_batch,
    rename_to_arkit,
)

MERGED = ("browInnerUp", "cheekPuff")
"""ARKit channels ICT splits into _L/_R halves."""


def _source_weights(source_names, arkit_names, weights: np.ndarray) -> np.ndarray:
    """(N, K) source weights: each source channel reads its ARKit channel's weight (both
    halves of a merged channel get the same weight). Built from the names alone."""
    column = {name: i for i, name in enumerate(arkit_names)}
    spelled = {"_L": "Left", "_R": "Right"}
    out = np.zeros((weights.shape[0], len(source_names)), np.float32)
    for j, name in enumerate(source_names):
        stem, suffix = name[:-2], name[-2:]
        if stem in MERGED and suffix in spelled:
            arkit = stem
        elif suffix in spelled:
            arkit = stem + spelled[suffix]
        else:
            arkit = name
        out[:, j] = weights[:, column[arkit]]
    return out


@pytest.fixture(scope="module")
def ict_arkit(ict_quartic):
    return rename_to_arkit(ict_quartic)


def test_ict_quartic_channels_are_the_arkit_names_without_tongue_out(ict_quartic, ict_arkit):
    assert len(ict_arkit.names) == len(set(ict_arkit.names)) == 51
    assert set(ict_arkit.names) == set(ARKIT_NAMES) - {"tongueOut"}
    assert ict_arkit.n_blendshapes == 51
    np.testing.assert_array_equal(np.asarray(ict_arkit.neutral), np.asarray(ict_quartic.neutral))
    np.testing.assert_array_equal(np.asarray(ict_arkit.faces), np.asarray(ict_quartic.faces))
    assert ict_arkit.units == ict_quartic.units
    # every corrective's drivers are distinct channels of the renamed rig
    for table in ict_arkit.correctives:
        rows = np.sort(np.asarray(table.indices), axis=1)
        assert rows.max() < 51 and np.all(rows[:, 1:] > rows[:, :-1])


def test_ict_quartic_renamed_evaluates_as_the_source_with_halves_duplicated(ict_quartic, ict_arkit):
    rng = np.random.default_rng(3)
    n = 8
    weights = rng.uniform(0.0, 1.0, (n, 51)).astype(np.float32)
    merged = [ict_arkit.names.index(name) for name in MERGED]
    # the merged channels at 0 or 1 (where a corrective on both halves folds exactly)
    weights[:, merged] = rng.integers(0, 2, (n, len(MERGED)))
    weights[0, merged] = 1.0  # at least one pose with both merged channels on
    source = _source_weights(ict_quartic.names, ict_arkit.names, weights)
    expected = np.asarray(evaluate_batch(ict_quartic, source))
    got = np.asarray(evaluate_batch(ict_arkit, weights))
    scale = np.abs(expected - np.asarray(ict_quartic.neutral)).max()
    assert scale > 0.5  # cm: the poses move the face
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-4)


def test_ict_quartic_merged_channel_is_the_sum_of_its_halves(ict_quartic, ict_arkit):
    names = list(ict_quartic.names)
    for channel in MERGED:
        halves = [names.index(f"{channel}_L"), names.index(f"{channel}_R")]
        # a corrective driven by both halves alone folds onto the channel's own shape
        both = np.zeros((ict_quartic.n_vertices, 3), np.float32)
        for table in ict_quartic.correctives:
            dense = table.to_dense(ict_quartic.n_vertices)
            for row, offsets in zip(np.asarray(table.indices), dense, strict=True):
                if set(row.tolist()) == set(halves):
                    both += offsets
        expected = np.asarray(ict_quartic.deltas)[halves].sum(axis=0) + both
        got = np.asarray(ict_arkit.deltas[ict_arkit.names.index(channel)])
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


def test_renaming_an_arkit_rig_gives_the_same_arrays(ict_arkit, data_dir):
    again = rename_to_arkit(ict_arkit)
    assert again.names == ict_arkit.names
    np.testing.assert_array_equal(np.asarray(again.neutral), np.asarray(ict_arkit.neutral))
    np.testing.assert_array_equal(np.asarray(again.deltas), np.asarray(ict_arkit.deltas))
    assert len(again.correctives) == len(ict_arkit.correctives)
    for a, b in zip(again.correctives, ict_arkit.correctives, strict=True):
        for field in ("indices", "vertices", "deltas"):
            np.testing.assert_array_equal(
                np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
            )
    # a sculpted ARKit rig (Rocketbox: 52 shapes, tongueOut included)
    head = np.load(data_dir / "rocketbox" / "Male_Adult_08_head.npz")
    names = tuple(str(n) for n in head["names"])
    rig = BlendshapeRig(head["neutral"], head["deltas"], (), names, head["faces"])
    renamed = rename_to_arkit(rig)
    assert renamed.names == rig.names
    np.testing.assert_array_equal(np.asarray(renamed.deltas), np.asarray(rig.deltas))
    np.testing.assert_array_equal(np.asarray(renamed.neutral), np.asarray(rig.neutral))
    assert renamed.correctives == ()


# --- a toy rig with correctives on both halves of one channel --------------------------------

TOY_NAMES = ("browInnerUp_L", "jawOpen", "browInnerUp_R", "eyeBlink_L", "myCustomShape")


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(7)
    v = 6
    neutral = rng.standard_normal((v, 3)).astype(np.float32)
    deltas = rng.standard_normal((len(TOY_NAMES), v, 3)).astype(np.float32)
    pairs = Corrective(
        # L x R (both halves alone), L x jaw, jaw x R (written in reverse order), blink x jaw
        [[0, 2], [0, 1], [1, 2], [3, 1]],
        np.arange(v),
        rng.standard_normal((4, v, 3)).astype(np.float32),
    )
    triples = Corrective(
        [[2, 1, 0], [0, 1, 3]],  # L x R x jaw (both halves), L x jaw x blink
        [1, 3, 4],
        rng.standard_normal((2, 3, 3)).astype(np.float32),
    )
    return BlendshapeRig(neutral, deltas, (pairs, triples), TOY_NAMES, None)


def _toy_expected(rig: BlendshapeRig, brow, jaw, blink, custom) -> np.ndarray:
    """The renamed toy rig at channel weights, written out term by term from the docstring:
    the halves summed, L x R folded to brow (w, not w^2), L x R x jaw to brow x jaw, L x jaw
    and jaw x R summed on brow x jaw."""
    d = np.asarray(rig.deltas, np.float64)
    p = rig.correctives[0].to_dense(rig.n_vertices).astype(np.float64)
    t = rig.correctives[1].to_dense(rig.n_vertices).astype(np.float64)
    return (
        np.asarray(rig.neutral, np.float64)
        + brow * (d[0] + d[2])
        + jaw * d[1]
        + blink * d[3]
        + custom * d[4]
        + brow * p[0]
        + brow * jaw * (p[1] + p[2] + t[0])
        + blink * jaw * p[3]
        + brow * jaw * blink * t[1]
    )


def test_toy_rig_fold_matches_the_documented_terms(toy):
    renamed = rename_to_arkit(toy)
    # unknown names are kept as they are; the channels in first-seen order
    assert renamed.names == ("browInnerUp", "jawOpen", "eyeBlinkLeft", "myCustomShape")
    rng = np.random.default_rng(0)
    for brow, jaw, blink, custom in rng.uniform(0, 1, (6, 4)):
        got = np.asarray(evaluate(renamed, np.array([brow, jaw, blink, custom], np.float32)))
        expected = _toy_expected(toy, brow, jaw, blink, custom)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


@pytest.mark.parametrize("brow", [0.0, 1.0])
def test_toy_rig_is_exact_with_the_merged_channel_at_0_or_1(toy, brow):
    renamed = rename_to_arkit(toy)
    rng = np.random.default_rng(int(brow))
    for jaw, blink, custom in rng.uniform(0, 1, (4, 3)):
        got = np.asarray(evaluate(renamed, np.array([brow, jaw, blink, custom], np.float32)))
        source = np.array([brow, jaw, brow, blink, custom], np.float32)
        np.testing.assert_allclose(got, np.asarray(evaluate(toy, source)), rtol=0, atol=1e-5)


def test_toy_rig_between_0_and_1_differs_by_the_folded_terms_only(toy):
    """Between 0 and 1 the fold shows w where the source shows w^2 (the docstring's
    approximation): the gap is (w - w^2) (L x R + jaw L x R x jaw), nothing else."""
    renamed = rename_to_arkit(toy)
    brow, jaw, blink, custom = 0.5, 0.7, 0.3, 0.9
    got = np.asarray(evaluate(renamed, np.array([brow, jaw, blink, custom], np.float32)))
    source = np.asarray(evaluate(toy, np.array([brow, jaw, brow, blink, custom], np.float32)))
    p = toy.correctives[0].to_dense(toy.n_vertices)
    t = toy.correctives[1].to_dense(toy.n_vertices)
    gap = (brow - brow**2) * (p[0] + jaw * t[0])
    assert np.abs(gap).max() > 1e-2
    np.testing.assert_allclose(got - source, gap, rtol=0, atol=1e-5)


def test_arkit_channels_groups_halves_in_first_seen_order():
    channels, index = arkit_channels(["cheekPuff_R", "jawOpen", "cheekPuff_L", "EyeBlinkLeft"])
    assert channels == ["cheekPuff", "jawOpen", "eyeBlinkLeft"]
    np.testing.assert_array_equal(index, [0, 1, 0, 2])
    assert [to_arkit(n) for n in ("cheekPuff_R", "cheekPuff_L")] == ["cheekPuff"] * 2


def test_rename_to_arkit_refuses_what_is_not_a_rig():
    with pytest.raises(TypeError, match="rig"):
        rename_to_arkit({"names": ["jawOpen"]})
