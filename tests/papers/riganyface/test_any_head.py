"""The any-head experiment's protocols: the scores against the artist's shapes of a head
(k = 0 and few-shot), the template of the same style, the face-crop fit, the orientation
cases, the command line's timing, the default-method rule and the committed table. The
``auto_rig`` calls and the orientation decision are replaced by recording stand-ins where the
protocol's bookkeeping is what is tested."""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
import pytest

from canrig_jax.autorig import AUTO_RIG_METHODS, OrientationError, Style
from canrig_jax.autorig._data import AutorigDataset, PoseSet
from canrig_jax.autorig._orientation import axis_rotations
from canrig_jax.data import ICTFaceModel
from canrig_jax.papers.riganyface import (
    EXAMPLE_ORDER,
    FEW_SHOT_KS,
    SculptedHead,
    any_head_table,
    choose_default_method,
    face_crop_fit,
    few_shot_rows,
    mean_few_shot,
    measure_cli_seconds,
    orientation_cases,
    sculpted_head_errors,
    template_row,
)
from canrig_jax.rig import BlendshapeRig

MODULE = "canrig_jax.papers.riganyface._any_head"
METHOD_NAMES = [cls.name for cls in AUTO_RIG_METHODS]
RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results" / "any_head"
NAMES = ("jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp", "mouthFunnel", "cheekPuff")


def _head(name: str = "head", seed: int = 0) -> SculptedHead:
    """Two components (cm): a 5 x 5 grid (the skin) and a separate triangle; each shape moves
    the grid by random amounts and the triangle not at all."""
    y, x = np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(25)], axis=1)
    faces = [[r * 5 + c, r * 5 + c + 1, r * 5 + c + 6] for r in range(4) for c in range(4)]
    faces += [[r * 5 + c, r * 5 + c + 6, r * 5 + c + 5] for r in range(4) for c in range(4)]
    vertices = np.concatenate([grid, [[10, 0, 0], [11, 0, 0], [10, 1, 0]]])
    faces = np.asarray(faces + [[25, 26, 27]], np.int32)
    deltas = np.zeros((len(NAMES), 28, 3))
    deltas[:, :25] = np.random.default_rng(seed).normal(0, 0.1, (len(NAMES), 25, 3))
    return SculptedHead(name, vertices, faces, deltas, NAMES)


def _dataset() -> AutorigDataset:
    ict = ICTFaceModel(np.eye(3, dtype=np.float32), np.asarray([[0, 1, 2]], np.int32),
                       np.zeros((1, 3, 3), np.float32), ("jawOpen",), ("Face",),
                       np.asarray([[0, 3]], np.int32), np.zeros(3, np.int32),
                       np.zeros(68, np.int32), np.arange(3, dtype=np.int32))  # fmt: skip
    return AutorigDataset(PoseSet(("jawOpen",), ((0,),)), ict, np.zeros((1, 3, 3)), [], {})


def _rig(head: SculptedHead, factor: float, names=NAMES) -> BlendshapeRig:
    return BlendshapeRig(head.vertices, factor * head.shapes(names), (), names, head.faces)


def test_the_table_is_the_committed_one():
    results = json.loads((RESULTS / "results.json").read_text())
    assert any_head_table(results) == (RESULTS / "table.md").read_text()


def test_scores_are_on_the_skin_and_by_name():
    head = _head()
    shuffled = tuple(reversed(NAMES))  # the rig's own order does not matter
    half = sculpted_head_errors(_rig(head, 0.5, shuffled), head, NAMES[:3])
    none = sculpted_head_errors(_rig(head, 0.0, shuffled), head, NAMES[:3])
    assert half["amplitude_median"] == pytest.approx(0.5) and none["amplitude_median"] == 0
    assert half["skin_mae_mm"] == pytest.approx(none["skin_mae_mm"] / 2)
    lengths = np.linalg.norm(head.deltas[:3, :25], axis=-1) * 10  # mm, skin only
    assert none["skin_mae_mm"] == pytest.approx(lengths.mean())
    assert none["skin_q95_mm"] == pytest.approx(np.percentile(lengths, 95))


def _auto_rig_stand_in(calls: list):
    """``auto_rig`` whose rig is the head's own shapes times a per-method factor; the examples
    given replace their shapes exactly."""
    factors = {"transfer": 0.8, "raf": 0.5, "transfer-residual": 0.9}

    def auto_rig(vertices, faces, *, method, examples=None, dataset=None,
                 orientation=None, landmarks=None):  # fmt: skip
        calls.append((method.name, None if examples is None else tuple(examples), orientation))
        head = _HEAD
        deltas = factors[method.name] * head.shapes(NAMES)
        for name, shape in (examples or {}).items():
            deltas[NAMES.index(name)] = shape
        rig = BlendshapeRig(head.vertices, deltas, (), NAMES, head.faces)
        return types.SimpleNamespace(
            rig=rig, style=Style(gain=factors[method.name]), orientation="upright",
            landmarks=np.zeros(68, int), fit={"by": "face", "rms_cm": 0.1},
        )  # fmt: skip

    return auto_rig


_HEAD = _head()


def test_few_shot_scores_each_k_on_the_shapes_not_given(monkeypatch):
    calls: list = []
    monkeypatch.setattr(f"{MODULE}.auto_rig", _auto_rig_stand_in(calls))
    methods, few, fit = few_shot_rows(_HEAD, _dataset(), log=lambda m: None)
    # the first call decides the orientation every other call reuses
    assert calls[0] == ("transfer", None, None)
    assert all(c[2] == "upright" for c in calls[1:])
    assert len(calls) == 1 + len(AUTO_RIG_METHODS) * len(FEW_SHOT_KS)
    assert fit == {"ok": True, "by": "face", "rms_cm": 0.1}
    assert list(methods) == ["no_motion", *METHOD_NAMES]
    raf = methods["raf"]
    assert raf == sculpted_head_errors(_rig(_HEAD, 0.5), _HEAD, NAMES)
    for method in METHOD_NAMES:
        assert list(few[method]) == [str(k) for k in FEW_SHOT_KS]
        for k in FEW_SHOT_KS:
            row, rest = few[method][str(k)], [n for n in NAMES if n not in EXAMPLE_ORDER[:k]]
            assert row["no_motion"] == sculpted_head_errors(_rig(_HEAD, 0.0), _HEAD, rest)
            factor = {"transfer": 0.8, "raf": 0.5, "transfer-residual": 0.9}[method]
            expected = sculpted_head_errors(_rig(_HEAD, factor), _HEAD, rest)
            assert {x: row[x] for x in expected} == pytest.approx(expected)
            assert row["style"]["gain"] == factor and row["seconds"] >= 0
    given = [c[1] for c in calls[1:]]
    assert given[: len(FEW_SHOT_KS)] == [None, *(EXAMPLE_ORDER[:k] for k in FEW_SHOT_KS[1:])]


def test_mean_few_shot_averages_over_heads():
    def rows(value):
        errors = {"skin_mae_mm": value, "active_mae_mm": 2 * value}
        few = {m: {"0": {**errors, "no_motion": errors, "style": {}}} for m in METHOD_NAMES}
        return {"no_motion": errors, "raf": errors}, few, {}

    methods, few = mean_few_shot([rows(1.0), rows(3.0)])
    assert methods["raf"] == {"skin_mae_mm": 2.0, "active_mae_mm": 4.0}
    assert few["raf"]["0"] == {
        "skin_mae_mm": 2.0,
        "active_mae_mm": 4.0,
        "no_motion": {"skin_mae_mm": 2.0, "active_mae_mm": 4.0},
    }


def test_template_row_carries_the_shared_shapes_and_scores_the_target(monkeypatch):
    source, target = _head("source", 1), _head("target", 2)
    source.names[-1] = "tongueOut"  # only the source has it: left out of the template
    made = {}

    class Template:
        @classmethod
        def from_rig(cls, dataset, rig, name):
            made.update(names=rig.names, deltas=np.asarray(rig.deltas), name=name)
            return "template"

    def auto_rig(vertices, faces, *, method, dataset):
        assert method == ("transfer", "template") and vertices is target.vertices
        return types.SimpleNamespace(rig=_rig(target, 1.0, NAMES[:5]))

    monkeypatch.setattr(f"{MODULE}.Template", Template)
    monkeypatch.setattr(f"{MODULE}.Transfer", lambda template: ("transfer", template))
    monkeypatch.setattr(f"{MODULE}.auto_rig", auto_rig)
    row, rig = template_row(target, source, _dataset())
    assert made["names"] == NAMES[:5] and made["name"] == "source"
    np.testing.assert_array_equal(made["deltas"], source.deltas[:5])
    assert row["skin_mae_mm"] == 0 and row["no_motion"]["skin_mae_mm"] > 0  # scored: 5 shapes
    assert rig.names == NAMES[:5]


def test_face_crop_fit_reports_a_refusal(monkeypatch):
    head = _head()
    fit = types.SimpleNamespace(rms=0.25)
    monkeypatch.setattr(f"{MODULE}.face_crop", lambda v, f: (v[:10], f[:2]))
    monkeypatch.setattr(f"{MODULE}.place_landmarks", lambda d, v, f: (None, fit, "inner face"))
    found = face_crop_fit(head, _dataset())
    assert found == {"ok": True, "by": "inner face", "rms_cm": 0.25, "vertices": 10}

    def refuse(dataset, vertices, faces):
        raise ValueError("vertices: the face does not fit")

    monkeypatch.setattr(f"{MODULE}.place_landmarks", refuse)
    refused = face_crop_fit(head, _dataset())
    assert refused == {"ok": False, "error": "vertices: the face does not fit", "vertices": 10}


def test_orientation_cases_count_recovered_refused_and_wrong(monkeypatch):
    """A stand-in decision that refuses heads turned upside down, answers 'as is' for heads
    turned to face -z (wrong unless nothing else was turned) and undoes every other turn."""
    vertices = np.random.default_rng(0).normal(size=(30, 3))
    faces = np.asarray([[0, 1, 2]], np.int32)

    def decide(dataset, moved, tris):
        turn = np.linalg.lstsq(vertices, moved, rcond=None)[0].T
        if turn[1, 1] < -0.5:
            raise OrientationError("upside down")
        if turn[2, 2] < -0.5:
            return types.SimpleNamespace(rotation=np.eye(3))
        proper = turn if np.linalg.det(turn) > 0 else turn @ np.diag([-1.0, 1, 1])
        return types.SimpleNamespace(rotation=proper.T)

    monkeypatch.setattr(f"{MODULE}.decide_orientation", decide)
    found = orientation_cases(
        {"a": (vertices, faces), "a_face_crop": (vertices, faces)}, None, log=lambda m: None
    )
    expected = {"cases": 48, "recovered": 0, "refused": 0, "silently_wrong": 0}
    for mirrored in (False, True):
        for rotation in axis_rotations():
            turn = rotation @ np.diag([-1.0, 1, 1]) if mirrored else rotation
            if turn[1, 1] < -0.5:
                expected["refused"] += 1
            elif turn[2, 2] < -0.5:
                expected["silently_wrong"] += 1
            else:
                expected["recovered"] += 1
    assert found["per_head"]["a"] == expected == found["per_head"]["a_face_crop"]
    assert found["cases"] == 96 and found["refused"] == 2 * expected["refused"] > 0
    assert found["refused_fraction_full_heads"] == expected["refused"] / 48


def test_measure_cli_seconds_warm_then_cold_on_makehuman(monkeypatch):
    calls = []

    def seconds(head, out_dir, env):
        calls.append((head.name, env.get("CANRIG_CACHE")))
        return float(len(calls))

    monkeypatch.setattr(f"{MODULE}._cli_seconds", seconds)
    heads = {"a": _head("a"), "makehuman": _head("mh")}
    found = measure_cli_seconds(heads, log=lambda m: None)
    assert found["a"] == {"vertices": 28, "warm_s": 2.0}  # the second of two runs
    assert found["makehuman"] == {"vertices": 28, "warm_s": 4.0, "cold_cache_s": 5.0}
    assert [c[0] for c in calls] == ["a", "a", "mh", "mh", "mh"]
    assert calls[-1][1].endswith("empty_cache") and calls[0][1] != calls[-1][1]
    with pytest.raises(ValueError, match="makehuman"):
        measure_cli_seconds({"a": _head("a")})


def test_the_rule_takes_the_smallest_worst_ratio_then_the_preference():
    def few(ratios):  # method -> (skin ratio, active ratio) on every case
        none = {"skin_mae_mm": 2.0, "active_mae_mm": 4.0}
        return {
            head: {
                m: {k: {"skin_mae_mm": 2.0 * s, "active_mae_mm": 4.0 * a, "no_motion": none}}
                for m, (s, a) in ratios.items()
            }
            for head, k in (("h1", "0"), ("h2", "3"))
        }

    cases = (("h1", "0"), ("h2", "3"))
    order = ("transfer", "transfer-residual", "raf")
    clear = few({"transfer": (0.95, 0.5), "raf": (0.5, 0.80), "transfer-residual": (0.9, 0.94)})
    default, worst = choose_default_method(clear, cases, 0.02, order)
    assert default == "raf" and worst == pytest.approx(
        {"transfer": 0.95, "raf": 0.80, "transfer-residual": 0.94}
    )
    close = few({"transfer": (0.95, 0.5), "raf": (0.93, 0.5), "transfer-residual": (0.94, 0.5)})
    assert choose_default_method(close, cases, 0.02, order)[0] == "transfer-residual"
    assert choose_default_method(close, cases, 0.05, order)[0] == "transfer"
    assert choose_default_method(close, cases, 0.0, order)[0] == "raf"
