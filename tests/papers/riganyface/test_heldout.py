"""The held-out evaluation protocols of the auto-rigging experiments, on small synthetic heads:
which rows models are evaluated as, how each row's predictions are gathered and scored per
split, the per-shape records, penetration where the truth has none and placement. The heavy
steps (correspondence, transfer, the network) are replaced by recording stand-ins where the
aggregation is what is tested."""

from __future__ import annotations

import types

import equinox as eqx
import jax
import numpy as np
import pytest

from canrig_jax.autorig import RigAnyFaceTrainOptions
from canrig_jax.autorig._data import AutorigDataset, PoseSet, RiggedHead
from canrig_jax.autorig._makehuman import MakeHumanHead
from canrig_jax.autorig._train import make_model
from canrig_jax.data import ICTFaceModel
from canrig_jax.mesh import MeshOperators
from canrig_jax.papers.riganyface import (
    ANCHOR_MODES,
    ANCHORED_RESIDUAL_MODELS,
    HELDOUT_SPLIT,
    RESIDUAL_MODEL,
    clean_penetration,
    evaluate_splits,
    evaluation_rows,
    heldout_predictions,
    heldout_shapes,
    load_checkpoint_rows,
    makehuman_shapes,
    placement_errors,
)

MODULE = "canrig_jax.papers.riganyface._heldout"
POSES = PoseSet(("browInnerUp", "eyeBlinkLeft", "jawOpen"), ((0,), (1,), (2,), (0, 2)))


def _model(residual: bool):
    """A RigAnyFace of the right type without initialising its weights (only ``residual`` is
    read by the row logic)."""
    options = RigAnyFaceTrainOptions(residual=residual)
    return eqx.filter_eval_shape(make_model, options, POSES.n_basis, 1.0)


def _head(index: int, n: int = 12, name: str | None = None) -> RiggedHead:
    """A strip of n vertices (cm, larger with ``index``), two triangles per cell; pose p moves
    vertex v by
    (index + 1) * (p + 1) * v / 100 cm along x; parts: the first half skin (0), then 5."""
    x = np.arange(n, dtype=float)
    vertices = np.stack([x % 6, x // 6, np.zeros(n)], axis=1) * (1 + index / 10)
    faces = np.asarray([[i, i + 1, i + 6] for i in range(5)], np.int32)
    p = np.arange(POSES.n_poses)[:, None]
    displacements = np.zeros((POSES.n_poses, n, 3))
    displacements[..., 0] = (index + 1) * (p + 1) * np.arange(n)[None] / 100
    parts = np.where(np.arange(n) < n // 2, 0, 5).astype(np.int32)
    return RiggedHead(
        name=name or f"test{index:02d}/strip",
        vertices=vertices,
        faces=faces,
        displacements=displacements,
        landmarks=np.zeros(68, np.int64),
        parts=parts,
        identity=np.zeros(2),
        topology="strip",
    )


def _dataset(per_split: int = 2) -> AutorigDataset:
    ict = ICTFaceModel(
        neutral=np.zeros((3, 3), np.float32),
        faces=np.asarray([[0, 1, 2]], np.int32),
        deltas=np.zeros((1, 3, 3), np.float32),
        names=("jawOpen",),
        part_names=("Face", "Teeth"),
        part_vertex_range=np.asarray([[0, 2], [2, 3]], np.int32),
        component_labels=np.zeros(3, np.int32),
        landmarks=np.zeros(68, np.int32),
        vertex_ids=np.arange(3, dtype=np.int32),
    )
    test = {
        "same_topology": [_head(i) for i in range(per_split)],
        "unseen_topology": [_head(10 + i) for i in range(per_split)],
    }
    return AutorigDataset(POSES, ict, np.zeros((4, 3, 3)), [], test)


def test_evaluation_rows_name_each_model_with_its_bases():
    """A pure model has one row without a base; the plain-DT residual model two (its training
    base, and the anchored one as ``_anchored``); an anchored residual model one, on its own
    base (the anchored key of its mode)."""
    models = {"raf": _model(False), RESIDUAL_MODEL: _model(True)}
    models.update({name: _model(True) for name in ANCHORED_RESIDUAL_MODELS})
    rows = evaluation_rows(models)
    assert rows["raf"] == ("raf", None)
    assert rows[RESIDUAL_MODEL] == (RESIDUAL_MODEL, "plain")
    assert rows[RESIDUAL_MODEL + "_anchored"] == (RESIDUAL_MODEL, "anchored")
    for name, mode in ANCHORED_RESIDUAL_MODELS.items():
        key = "anchored" if mode == "vertex" else f"anchored_{mode}"
        assert rows[name] == (name, key)
    assert set(ANCHORED_RESIDUAL_MODELS.values()) == set(ANCHOR_MODES)
    assert len(rows) == len(models) + 1


def _scale(vertices) -> float:
    """The stand-in unit-sphere scale of a head (cm): its largest coordinate + 1."""
    return float(np.abs(vertices).max()) + 1.0


_OPERATORS: dict[int, MeshOperators] = {}


def _operators(k: int) -> MeshOperators:
    """A stand-in ``MeshOperators`` of the right type per eigenvector count ``k`` (only passed
    through: which one arrives says which ``k`` it was made with)."""
    return _OPERATORS.setdefault(k, object.__new__(MeshOperators))


def _stand_ins(monkeypatch, calls: list) -> None:
    """Replace correspondence, transfer, copying, generation, operators and penetration by
    functions of the head, so each row's predictions are known: copy = truth, DT = 1.1 truth,
    anchored DT = 0.9 truth, the i-th row of ``rows`` = (1 + 0.01 i) truth; penetration = the
    largest displacement times the number of part names."""

    def bases(dataset, head, correspondence, anchors=("vertex",)):
        out = {"plain": 1.1 * head.displacements}
        for mode in anchors:
            key = "anchored" if mode == "vertex" else f"anchored_{mode}"
            out[key] = 0.9 * head.displacements
        return out

    def generate(models, rows, poses, head, bases, operators=None, placement=None):
        calls.append((head.name, operators))
        return {
            name: types.SimpleNamespace(displacements=(1 + 0.01 * i) * head.displacements)
            for i, name in enumerate(rows)
        }

    monkeypatch.setattr(f"{MODULE}.head_correspondence", lambda *a: "correspondence")
    monkeypatch.setattr(f"{MODULE}.transfer_bases", bases)
    monkeypatch.setattr(f"{MODULE}.copy_poses", lambda d, head, c: head.displacements.copy())
    monkeypatch.setattr(f"{MODULE}.generate_rows", generate)
    monkeypatch.setattr(
        f"{MODULE}.head_inputs", lambda v, f, k: (None, _operators(k), None, _scale(v))
    )
    monkeypatch.setattr(
        f"{MODULE}.penetration", lambda head, d, parts: float(np.abs(d).max() * len(parts))
    )


def test_evaluate_splits_scores_every_row_on_both_splits(monkeypatch):
    calls: list = []
    _stand_ins(monkeypatch, calls)
    dataset = _dataset()
    rows = {"raf": ("raf", None), "res": ("res", "plain")}
    found = evaluate_splits(dataset, {}, rows, ("vertex", "part"), k=7)
    names = ["copy_deltas", "deformation_transfer", "deformation_transfer_anchored"]
    names += ["deformation_transfer_anchored_part", *rows]
    assert list(found["test"]) == names
    factors = {"copy_deltas": 1.0, "deformation_transfer": 1.1, "raf": 1.0, "res": 1.01}
    factors.update(deformation_transfer_anchored=0.9, deformation_transfer_anchored_part=0.9)
    for split, heads in dataset.test.items():
        for name, factor in factors.items():
            errors = found["test"][name][split]
            per_head = [abs(factor - 1) * np.linalg.norm(h.displacements, axis=-1) for h in heads]
            distance = np.concatenate(per_head, 1)  # cm
            assert errors["mae_mm"] == pytest.approx(10 * distance.mean(), abs=1e-12)
            assert errors["q95_mm"] == pytest.approx(10 * np.percentile(distance, 95), abs=1e-12)
            assert errors["heads"] == len(heads)
            # unit sphere x 1000: each head's distances divided by its own scale
            unit = np.concatenate(
                [d / _scale(h.vertices) for d, h in zip(per_head, heads, strict=True)], 1
            )
            assert errors["mae_unit_sphere_x1000"] == pytest.approx(1000 * unit.mean(), abs=1e-12)
    # the network ran on each head's own operators (k eigenvectors), once per head
    assert len(calls) == 4 and all(c[1] is _operators(7) for c in calls)
    # penetration: the rows' and the truth's, mean over all four heads
    heads = [h for split in dataset.test.values() for h in split]
    biggest = [np.abs(h.displacements).max() * 2 for h in heads]  # two part names
    assert found["penetration"] == pytest.approx(
        {"raf": np.mean(biggest), "res": 1.01 * np.mean(biggest), "ground_truth": np.mean(biggest)}
    )
    # the held-out split's predictions, no motion first, and its truth
    unseen = dataset.test[HELDOUT_SPLIT]
    assert list(found["predictions"]) == ["no_motion", *names]
    assert all(not p.any() for p in found["predictions"]["no_motion"])
    np.testing.assert_allclose(found["predictions"]["res"][1], 1.01 * unseen[1].displacements)
    assert all(t is h.displacements for t, h in zip(found["truth"], unseen, strict=True))
    head, example = found["examples"]["same_topology"]
    assert head is dataset.test["same_topology"][0] and list(example) == names


def test_heldout_predictions_default_rows_put_a_residual_model_on_every_base(monkeypatch):
    calls: list = []
    _stand_ins(monkeypatch, calls)
    dataset = _dataset()
    models = {"run/raf": _model(False), "run/res": _model(True)}
    predicted, truth = heldout_predictions(dataset, models, ("vertex", "skin_vertex"), copy=True)
    assert list(predicted) == [
        "no_motion",
        "copy_deltas",
        "deformation_transfer",
        "deformation_transfer_anchored",
        "deformation_transfer_anchored_skin_vertex",
        "run/raf",
        "run/res",
        "run/res+anchored_base",
        "run/res+anchored_skin_vertex_base",
    ]
    unseen = dataset.test[HELDOUT_SPLIT]
    assert len(truth) == len(unseen) and all(len(p) == len(unseen) for p in predicted.values())
    np.testing.assert_array_equal(truth[1], unseen[1].displacements)
    # without copy no copied row; given rows replace the default ones
    predicted, _ = heldout_predictions(dataset, models, ("vertex",), rows={"x": ("run/raf", None)})
    assert list(predicted) == [
        "no_motion",
        "deformation_transfer",
        "deformation_transfer_anchored",
        "x",
    ]


def test_heldout_shapes_are_ratios_of_the_first_poses_on_the_skin_mean_over_heads():
    heads = [_head(0), _head(3)]
    predicted = {
        "no_motion": [np.zeros_like(h.displacements) for h in heads],
        "double": [2 * h.displacements for h in heads],
        "half_and_noise": [h.displacements * 0.5 for h in heads],
    }
    for p in predicted["half_and_noise"]:
        p[POSES.n_basis :] = 99.0  # combination poses are not single shapes: never read
    shapes = heldout_shapes(heads, predicted, POSES)
    assert shapes["labels"] == list(POSES.basis_names)
    assert shapes["upper_face"] == [True, True, False]
    assert set(shapes["methods"]) == {"double", "half_and_noise"}
    double, half = shapes["methods"]["double"], shapes["methods"]["half_and_noise"]
    np.testing.assert_allclose(double["amplitude_ratio"], 2.0)
    np.testing.assert_allclose(double["peak_ratio"], 2.0)
    np.testing.assert_allclose(half["peak_ratio"], 0.5)
    skin = heads[0].parts <= 1
    expected = np.mean(
        [np.linalg.norm(h.displacements[:3][:, skin], axis=-1).mean(1) * 10 for h in heads], 0
    )
    np.testing.assert_allclose(double["skin_mae_mm"], expected)
    np.testing.assert_allclose(half["skin_mae_mm"], expected / 2)


def test_makehuman_shapes_peak_ratio_and_regions():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(3, 8, 3))
    skin = np.arange(8) < 6
    mh = MakeHumanHead(
        neutral=np.zeros((8, 3), np.float32),
        faces=np.asarray([[0, 1, 2]], np.int32),
        deltas=np.zeros((1, 8, 3), np.float32),
        names=("jawOpen",),
        component_labels=np.where(skin, 0, 1),  # the largest component is the skin
    )
    assert np.array_equal(mh.skin, skin)
    labels = ["eyeBlinkLeft", "jawOpen", "cheekSquintLeft"]
    shapes = makehuman_shapes((mh, truth, {"half": truth / 2, "same": truth}, labels))
    assert shapes["labels"] == labels and shapes["upper_face"] == [True, False, True]
    peak = np.linalg.norm(truth[:, skin], axis=-1).max(1) * 10
    np.testing.assert_allclose(shapes["target_peak_mm"], peak)
    np.testing.assert_allclose(shapes["methods"]["half"]["peak_ratio"], 0.5)
    np.testing.assert_allclose(shapes["methods"]["half"]["amplitude_ratio"], 0.5)
    np.testing.assert_allclose(shapes["methods"]["same"]["skin_mae_mm"], 0.0, atol=1e-12)


def test_clean_penetration_counts_only_the_selected_poses_and_vertices(monkeypatch):
    """Per head, the selected poses and inner vertices (stand-in ``penetration_free_set``);
    a row's outside pairs (stand-in ``inner_outside``: a vertex is out when moved > 0.3 cm
    along x) counted only there; the plain fraction over everything."""
    heads = [_head(0, name="a/strip"), _head(1, name="b/strip")]
    selection = {
        "a/strip": (np.asarray([0, 1]), np.arange(6) < 4),
        "b/strip": (np.asarray([0]), np.arange(6) >= 1),
    }
    monkeypatch.setattr(f"{MODULE}.penetration_free_set", lambda head, parts: selection[head.name])
    monkeypatch.setattr(
        f"{MODULE}.inner_outside", lambda head, d, parts: d[:, 6:, 0] > 0.3
    )  # (P, 6 inner vertices)
    predicted = {"moved": [h.displacements * 3 for h in heads]}
    found = clean_penetration(heads, predicted, POSES, ("Face", "Teeth"))
    outs, plain = [], []
    for head, p in zip(heads, predicted["moved"], strict=True):
        poses, vertices = selection[head.name]
        outside = p[:, 6:, 0] > 0.3
        outs.append(outside[poses][:, vertices])
        plain.append(outside.mean())
    clean = found["penetration_clean"]["moved"]
    assert clean["fraction"] == pytest.approx(np.concatenate([o.ravel() for o in outs]).mean())
    assert clean["poses_with_any"] == pytest.approx(np.mean([r.any() for o in outs for r in o]))
    assert 0 < clean["fraction"] < 1
    assert found["penetration_remeasured"]["moved"] == pytest.approx(np.mean(plain))
    protocol = found["penetration_clean_protocol"]
    assert protocol["poses_per_head"] == [2, 1] and protocol["inner_vertices_per_head"] == [4, 5]
    assert protocol["poses_selected_on_every_head"] == [POSES.labels[0]]
    assert set(found["penetration_clean"]) == {"moved", "ground_truth"}


def test_placement_compares_whole_and_cut_heads_on_the_same_vertices(monkeypatch):
    """A stand-in network whose prediction depends only on each vertex's position (and the
    placement): the whole head, compared on the vertices above the cut, scores exactly as
    the cut head; the two placements differ."""
    rows = 8
    y, x = np.meshgrid(np.arange(rows, dtype=float), np.arange(4, dtype=float), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    faces = []
    for r in range(rows - 1):
        for c in range(3):
            a, b, d, e = r * 4 + c, r * 4 + c + 1, (r + 1) * 4 + c, (r + 1) * 4 + c + 1
            faces += [[a, b, e], [a, e, d]]
    landmarks = np.zeros(68, np.int64)
    landmarks[8] = 4 * 4 + 1  # the chin at y = 4 cm: rows above 3 cm kept (1 cm margin)
    displacements = np.zeros((POSES.n_poses, vertices.shape[0], 3))
    displacements[..., 1] = 0.1
    head = RiggedHead("h", vertices, np.asarray(faces, np.int32), displacements, landmarks,
                      np.zeros(vertices.shape[0], np.int32), np.zeros(2), "grid")  # fmt: skip
    dataset = _dataset()
    dataset.test[HELDOUT_SPLIT] = [head]

    def generate(model, poses, v, f, placement=None):
        factor = 1.0 if placement is None else 2.0
        out = np.zeros((poses.n_poses, len(v), 3))
        out[..., 1] = factor * 0.01 * v[:, 1]
        return types.SimpleNamespace(displacements=out)

    monkeypatch.setattr(f"{MODULE}.generate_rig", generate)
    monkeypatch.setattr(f"{MODULE}.face_placement", lambda d, v, f: (v.mean(0), 5.0))
    stats, protocol = placement_errors(_model(False), POSES, dataset)
    assert set(stats) == {"whole/bounding_box", "whole/face", "cut/bounding_box", "cut/face"}
    assert stats["whole/bounding_box"] == pytest.approx(stats["cut/bounding_box"])
    assert stats["whole/face"] == pytest.approx(stats["cut/face"])
    kept = vertices[:, 1] >= 4
    expected = np.abs(0.01 * vertices[kept, 1] - 0.1).mean() * 10
    assert stats["cut/bounding_box"]["mae_mm"] == pytest.approx(expected)
    assert stats["cut/face"]["mae_mm"] != pytest.approx(expected)
    assert protocol["scale_cm"]["cut"]["face_cm"] == 5.0 and protocol["heads"] == 1


def test_load_checkpoint_rows_names_rows_by_folder_and_stem(tmp_path, monkeypatch):
    import shutil

    from canrig_jax.autorig import DEFAULT_CHECKPOINT, load_riganyface

    path = tmp_path / "run" / "checkpoint_raf.eqx"
    path.parent.mkdir()
    shutil.copy(DEFAULT_CHECKPOINT, path)
    rows = load_checkpoint_rows([path])
    assert list(rows) == ["run/checkpoint_raf"]
    model, header = rows["run/checkpoint_raf"]
    expected, _, expected_header = load_riganyface(path)
    assert header["options"] == expected_header["options"] and not model.residual
    leaves = [jax.tree.leaves(eqx.filter(m, eqx.is_array)) for m in (model, expected)]
    assert len(leaves[0]) == len(leaves[1]) > 0
    for a, b in zip(*leaves, strict=True):
        np.testing.assert_array_equal(a, b)
    # a missing file is named before any checkpoint is read
    loads = []
    monkeypatch.setattr(f"{MODULE}.load_riganyface", lambda p: loads.append(p))
    with pytest.raises(ValueError, match="paths: no checkpoint .*missing"):
        load_checkpoint_rows([path, tmp_path / "missing.eqx"])
    assert loads == []
