"""Visemes and Ready Player Me extras: each exactly its documented sum of ARKit shapes.

The table is read from ``docs/guides/avatars.md`` (what a user reads), compared with
``rig.EXTRA_SHAPES``, and each extra shape is recomputed here from the rig's own shapes.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from canrig_jax import CanrigWarning
from canrig_jax.data import ARKIT_NAMES
from canrig_jax.rig import EXTRA_SHAPES, BlendshapeRig, with_extra_shapes

DOC = Path(__file__).resolve().parents[2] / "docs" / "guides" / "avatars.md"
ISSUE_VISEMES = ("viseme_sil", "viseme_PP", "viseme_FF", "viseme_TH", "viseme_DD", "viseme_kk",
                 "viseme_CH", "viseme_SS", "viseme_nn", "viseme_RR", "viseme_aa", "viseme_E",
                 "viseme_I", "viseme_O", "viseme_U")  # fmt: skip
ISSUE_RPM = ("mouthOpen", "mouthSmile", "eyesClosed", "eyesLookUp", "eyesLookDown")


def _documented() -> dict[str, dict[str, dict[str, float]]]:
    text = DOC.read_text()
    block = text[text.index("<!-- extras table -->") : text.index("<!-- end extras table -->")]
    table: dict[str, dict[str, dict[str, float]]] = {}
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[0].startswith("`"):
            continue
        terms = {name: float(weight) for weight, name in re.findall(r"([0-9.]+) `(\w+)`", cells[2])}
        table.setdefault(cells[1], {})[cells[0].strip("`")] = terms
    return table


def _arkit_rig(names=ARKIT_NAMES, seed=0):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(30, 3)).astype(np.float32)
    deltas = rng.normal(size=(len(names), 30, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 4]], np.int32)
    return BlendshapeRig(neutral, deltas, (), tuple(names), faces)


def test_the_docs_table_is_the_code_table_and_names_the_issue_targets():
    documented = _documented()
    assert documented == EXTRA_SHAPES
    assert tuple(EXTRA_SHAPES["visemes"]) == ISSUE_VISEMES
    assert tuple(EXTRA_SHAPES["rpm"]) == ISSUE_RPM
    used = {k for table in EXTRA_SHAPES.values() for terms in table.values() for k in terms}
    assert used <= set(ARKIT_NAMES)


def test_each_extra_is_exactly_its_combination():
    rig = _arkit_rig()
    out = with_extra_shapes(rig, ("visemes", "rpm"))
    assert out.names == (*rig.names, *ISSUE_VISEMES, *ISSUE_RPM)
    deltas = np.asarray(rig.deltas, np.float64)
    np.testing.assert_array_equal(np.asarray(out.deltas)[: rig.n_blendshapes], rig.deltas)
    for table in _documented().values():
        for name, terms in table.items():
            expected = sum(
                (w * deltas[rig.names.index(k)] for k, w in terms.items()), np.zeros((30, 3))
            )
            got = np.asarray(out.deltas)[out.names.index(name)]
            np.testing.assert_array_equal(got, expected.astype(np.float32), err_msg=name)
    np.testing.assert_array_equal(np.asarray(out.deltas)[out.names.index("viseme_sil")], 0.0)


def test_a_missing_term_is_left_out_and_named():
    names = [n for n in ARKIT_NAMES if n != "tongueOut"]
    rig = _arkit_rig(names)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = with_extra_shapes(rig, "visemes")
    [message] = [str(w.message) for w in caught if issubclass(w.category, CanrigWarning)]
    assert "tongueOut" in message
    th = EXTRA_SHAPES["visemes"]["viseme_TH"]
    expected = sum(w * np.asarray(rig.deltas, np.float64)[names.index(k)]
                   for k, w in th.items() if k != "tongueOut")  # fmt: skip
    got = np.asarray(out.deltas)[out.names.index("viseme_TH")]
    np.testing.assert_array_equal(got, expected.astype(np.float32))
    assert "mouthOpen" not in out.names  # only the sets asked for


def test_bad_sets_and_clashes_are_refused():
    rig = _arkit_rig()
    with pytest.raises(ValueError, match="extras: unknown sets"):
        with_extra_shapes(rig, ("visemes", "oculus"))
    twice = with_extra_shapes(rig, "rpm")
    with pytest.raises(ValueError, match="rig: already has shapes named"):
        with_extra_shapes(twice, "rpm")
    with pytest.raises(ValueError, match="has none of"):
        with_extra_shapes(_arkit_rig(["browDownLeft"]), "rpm")
