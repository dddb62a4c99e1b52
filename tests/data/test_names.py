"""ARKit name canonicalisation and name-based weight retargeting."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrig_jax.data import (
    ARKIT_NAMES,
    arkit_name_of,
    load_ict,
    load_livelinkface,
    retarget_weights,
    to_arkit,
)


@pytest.fixture(scope="module")
def ict_names(data_dir):
    return load_ict(data_dir).names


@pytest.fixture(scope="module")
def unreal_names(data_dir):
    return load_livelinkface(data_dir).names


def _unreal(name):
    return name[0].upper() + name[1:]


def test_arkit_names_are_52_unique_camelcase():
    assert len(ARKIT_NAMES) == 52 == len(set(ARKIT_NAMES))
    assert ARKIT_NAMES[0] == "eyeBlinkLeft" and ARKIT_NAMES[-1] == "tongueOut"
    assert all(n[0].islower() and "_" not in n for n in ARKIT_NAMES)


def test_round_trips():
    for name in ARKIT_NAMES:
        assert to_arkit(name) == name
        assert to_arkit(_unreal(name)) == name
    assert to_arkit("eyeBlink_L") == "eyeBlinkLeft"
    assert to_arkit("mouthSmile_R") == "mouthSmileRight"
    assert to_arkit("jawOpen") == "jawOpen"
    assert to_arkit("browInnerUp_R") == to_arkit("BrowInnerUp") == "browInnerUp"
    assert to_arkit("cheekPuff_L") == "cheekPuff"


def test_all_ict_names_map(ict_names):
    assert len(ict_names) == 53
    mapped = [to_arkit(n) for n in ict_names]
    assert set(mapped) == set(ARKIT_NAMES) - {"tongueOut"}
    # rebuild the ICT spelling independently: Left/Right suffix -> _L/_R
    for n, a in zip(ict_names, mapped, strict=True):
        if n.endswith(("_L", "_R")) and a not in ("browInnerUp", "cheekPuff"):
            assert a == n[:-2] + ("Left" if n.endswith("_L") else "Right")
        elif not n.endswith(("_L", "_R")):
            assert a == n


def test_all_unreal_names_map_in_arkit_order(unreal_names):
    assert len(unreal_names) == 52
    assert tuple(to_arkit(n) for n in unreal_names) == ARKIT_NAMES
    assert tuple(_unreal(a) for a in ARKIT_NAMES) == unreal_names


def test_unknown_names_raise_listing_them():
    with pytest.raises(ValueError, match="eyeBlinkLeftt"):
        to_arkit("eyeBlinkLeftt")
    with pytest.raises(ValueError, match=r"foo.*bar"):
        retarget_weights(np.zeros(3), ["foo", "jawOpen", "bar"], ["jawOpen"])
    with pytest.raises(ValueError, match="target_names"):
        retarget_weights(np.zeros(1), ["jawOpen"], ["EyeBlink_L"])


def test_split_targets_get_the_same_value(ict_names):
    weights = np.linspace(0.0, 1.0, 52, dtype=np.float32)
    with pytest.warns(UserWarning, match="tongueOut"):
        out, report = retarget_weights(weights, ARKIT_NAMES, ict_names)
    col = {n: out[i] for i, n in enumerate(ict_names)}
    src = dict(zip(ARKIT_NAMES, weights, strict=True))
    assert col["browInnerUp_L"] == col["browInnerUp_R"] == src["browInnerUp"]
    assert col["cheekPuff_L"] == col["cheekPuff_R"] == src["cheekPuff"]
    assert col["eyeBlink_L"] == src["eyeBlinkLeft"]
    assert report.unused_source == ("tongueOut",)
    assert report.missing_target == () and report.averaged == ()


def test_tongue_out_unused_for_ict(unreal_names, ict_names):
    with pytest.warns(UserWarning, match="TongueOut"):
        _, report = retarget_weights(np.zeros((2, 52)), unreal_names, ict_names)
    assert report.unused_source == ("TongueOut",)


def test_ict_to_arkit_averages_halves_and_missing_policy(ict_names):
    rng = np.random.default_rng(1)
    w = rng.uniform(size=(4, 53)).astype(np.float32)
    with pytest.raises(ValueError, match="tongueOut"):
        retarget_weights(w, ict_names, ARKIT_NAMES)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing in the source goes unused
        out, report = retarget_weights(w, ict_names, ARKIT_NAMES, missing="zero")
    assert out.shape == (4, 52) and out.dtype == np.float32
    assert report.missing_target == ("tongueOut",) and report.unused_source == ()
    assert set(report.averaged) == {
        ("browInnerUp_L", "browInnerUp_R"),
        ("cheekPuff_L", "cheekPuff_R"),
    }
    i = {n: k for k, n in enumerate(ict_names)}
    j = {n: k for k, n in enumerate(ARKIT_NAMES)}
    np.testing.assert_array_equal(out[:, j["tongueOut"]], 0.0)
    np.testing.assert_allclose(
        out[:, j["browInnerUp"]],
        (w[:, i["browInnerUp_L"]] + w[:, i["browInnerUp_R"]]) / 2,
        rtol=1e-6,
    )
    np.testing.assert_array_equal(out[:, j["mouthSmileRight"]], w[:, i["mouthSmile_R"]])


@settings(max_examples=30, deadline=None)
@given(
    perm=st.permutations(list(range(52))),
    weights=st.lists(st.floats(0, 1, width=32), min_size=52, max_size=52),
)
def test_retarget_is_a_permutation_by_name(perm, weights):
    source = [_unreal(n) for n in ARKIT_NAMES]
    target = [ARKIT_NAMES[p] for p in perm]
    w = np.asarray(weights, dtype=np.float32)
    out, report = retarget_weights(w, source, target)
    np.testing.assert_array_equal(out, w[list(perm)])
    assert report == type(report)((), (), ())


def test_round_trip_arkit_ict_arkit(ict_names):
    w = np.random.default_rng(2).uniform(size=(5, 52)).astype(np.float32)
    with pytest.warns(UserWarning):
        ict, _ = retarget_weights(w, ARKIT_NAMES, ict_names)
    back, _ = retarget_weights(ict, ict_names, ARKIT_NAMES, missing="zero")
    np.testing.assert_allclose(back[:, :-1], w[:, :-1], rtol=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "argument"),
    [
        ({"weights": np.zeros(3)}, "weights"),
        ({"weights": np.array([np.nan])}, "weights"),
        ({"missing": "ignore"}, "missing"),
        ({"source_names": "jawOpen"}, "source_names"),
    ],
)
def test_bad_inputs_raise(kwargs, argument):
    args = {"weights": np.zeros(1), "source_names": ["jawOpen"], "target_names": ["jawOpen"]}
    args.update(kwargs)
    with pytest.raises(ValueError, match=argument):
        retarget_weights(**args)


def test_arkit_name_of_prefixed_names():
    """Names from rig files: a numbered ``AK_NN_`` prefix (Rocketbox), a blend-shape node or
    Maya namespace prefix, in any accepted spelling; other shapes give None."""
    for i, name in enumerate(ARKIT_NAMES):
        unreal = name[0].upper() + name[1:]
        assert arkit_name_of(f"AK_{i + 1:02d}_{unreal}") == name
        assert arkit_name_of(f"blendShape1.AK_{i + 1:02d}_{unreal}") == name
        assert arkit_name_of(f"head:{name}") == name
        assert to_arkit(f"AK_{i + 1:02d}_{unreal}") == name
    assert arkit_name_of("eyeBlink_L") == "eyeBlinkLeft"  # ICT, as to_arkit
    for other in ("AA_VI_00_Sil", "AK_JawOpen", "Fcl_ALL_Joy", "", "jawopen", "AK_25_"):
        assert arkit_name_of(other) is None
    with pytest.raises(ValueError, match="AK_09_EyeBlinkLeft"):
        to_arkit("AA_VI_00_Sil")
    with pytest.raises(TypeError, match="name"):
        arkit_name_of(3)
