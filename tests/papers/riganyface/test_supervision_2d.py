"""The 2D-supervision experiment's protocols: its command line, which heads keep their rig,
the two training runs' stages, the chunk-budget check, the evaluation's scores and the
committed table; the rasteriser checks themselves on the ICT head (slow)."""

from __future__ import annotations

import argparse
import json
import types
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

from canrig_jax.autorig import RigAnyFaceTrainOptions
from canrig_jax.autorig._data import AutorigDataset, PoseSet, RiggedHead
from canrig_jax.autorig._supervision_2d import Supervision2DOptions
from canrig_jax.autorig._train import TrainingSet, make_model
from canrig_jax.data import ICTFaceModel
from canrig_jax.papers.riganyface import (
    SUPERVISION_2D_RUNS,
    chunk_overflow,
    evaluate_2d,
    parse_supervision_2d_args,
    rasteriser_checks,
    rigged_heads,
    supervision_2d_options,
    supervision_2d_table,
    train_2d_run,
)

MODULE = "canrig_jax.papers.riganyface._supervision_2d"
RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results" / "autorig_2d"
POSES = PoseSet(("jawOpen", "eyeBlink_L"), ((0,), (1,), (0, 1)))


def _head(name: str, scale: float) -> RiggedHead:
    """A triangle pair (cm); pose p moves every vertex by scale * (p + 1) / 10 along y."""
    vertices = np.asarray([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float) * scale
    displacements = np.zeros((POSES.n_poses, 4, 3))
    displacements[..., 1] = scale * (np.arange(POSES.n_poses)[:, None] + 1) / 10
    return RiggedHead(name, vertices, np.asarray([[0, 1, 2], [1, 3, 2]], np.int32),
                      displacements, np.zeros(68, np.int64), np.zeros(4, np.int32), np.zeros(2),
                      name.split("/")[1])  # fmt: skip


def _dataset(train=(), test=()) -> AutorigDataset:
    ict = ICTFaceModel(np.eye(3, dtype=np.float32), np.asarray([[0, 1, 2]], np.int32),
                       np.zeros((1, 3, 3), np.float32), ("jawOpen",), ("Face",),
                       np.asarray([[0, 3]], np.int32), np.zeros(3, np.int32),
                       np.zeros(68, np.int32), np.arange(3, dtype=np.int32))  # fmt: skip
    return AutorigDataset(
        POSES, ict, np.zeros((3, 3, 3)), list(train), {"unseen_topology": list(test)}
    )


def _model():
    return eqx.filter_eval_shape(make_model, RigAnyFaceTrainOptions(), POSES.n_basis, 1.0)


def test_the_table_is_the_committed_one():
    results = json.loads((RESULTS / "results.json").read_text())
    assert supervision_2d_table(results) == (RESULTS / "table.md").read_text()
    rasteriser_only = {"rasteriser": results["rasteriser"]}
    text = supervision_2d_table(rasteriser_only)
    assert "## Rasteriser" in text and "## Training" not in text


def test_quick_makes_the_run_tiny_and_the_flags_make_the_2d_options():
    parse = lambda *argv: parse_supervision_2d_args(argparse.ArgumentParser(), list(argv))  # noqa: E731
    args = parse("--views", "0", "20", "45", "--poses-2d", "3", "--rasteriser", "soft")
    opts = supervision_2d_options(args)
    assert (opts.yaw_degrees, opts.poses_2d, opts.rasteriser, opts.image_size) == (
        (0.0, 20.0, 45.0), 3, "soft", 256
    )  # fmt: skip
    quick = parse("--quick", "--steps", "400", "--train-identities", "8")
    assert (quick.train_identities, quick.rigged_identities, quick.test_identities) == (2, 1, 1)
    assert quick.steps == 4 and supervision_2d_options(quick).image_size == 24


def test_rigged_heads_are_every_resolution_of_the_first_identities():
    names = ["train01/a", "train01/b", "train00/a", "train00/b", "train02/a", "train02/b"]
    dataset = _dataset(train=[_head(n, 1.0) for n in names])
    assert rigged_heads(dataset, 1) == [2, 3]  # train00, in sorted order of identities
    assert rigged_heads(dataset, 2) == [0, 1, 2, 3]
    assert rigged_heads(dataset, 0) == []


def test_the_two_stage_run_starts_stage_two_from_stage_one(monkeypatch, tmp_path):
    calls = []
    models = iter([_model(), _model(), _model()])

    def train(data, faces, poses, rigged, options, opts2d, *, stage, init=None, checkpoint,
              progress):  # fmt: skip
        model = next(models)
        calls.append((stage, options.steps, options.warmup_steps, init, checkpoint))
        history = [{"step": s, "error_mm": 1.0} for s in (10, options.steps)]
        return model, options.steps, 60.0, history

    monkeypatch.setattr(f"{MODULE}.train_2d", train)
    data = object.__new__(TrainingSet)
    common = dict(folder=tmp_path, steps=300, stage1_fraction=0.4, seed=1, progress=False)
    opts = Supervision2DOptions()
    faces = np.zeros((1, 1, 3), np.int32)  # only passed through
    model, info = train_2d_run("3d_only", data, faces, POSES, [0], opts, **common)
    assert calls == [("3d", 300, 50, None, tmp_path / "checkpoint_3d_only.eqx")]
    assert (info["steps"], info["seconds"], [r["step"] for r in info["history"]]) == (
        300, 60.0, [10, 300]
    )  # fmt: skip
    calls.clear()
    model, info = train_2d_run("2d_unrigged_plus_3d", data, faces, POSES, [0], opts, **common)
    (stage1, steps1, _, init1, path1), (stage2, steps2, warm2, init2, path2) = calls
    assert (stage1, steps1, init1, path1.name) == ("2d", 120, None, "checkpoint_2d_stage1.eqx")
    assert (stage2, steps2, warm2, path2.name) == ("3d+2d", 180, 36, "checkpoint_2d_stage2.eqx")
    assert init2 is not None and init2 is not model  # stage 2 starts from stage 1's model
    assert (info["steps"], info["stage1_steps"], info["stage2_steps"]) == (300, 120, 180)
    assert info["seconds"] == 120.0
    assert [r["step"] for r in info["history"]] == [10, 120, 130, 300]  # counted from stage 1
    with pytest.raises(ValueError, match="name: expected one of"):
        train_2d_run("2d_only", data, faces, POSES, [0], opts, **common)
    assert SUPERVISION_2D_RUNS == ("3d_only", "2d_unrigged_plus_3d")


def test_chunk_overflow_is_the_worst_over_heads_poses_and_views(monkeypatch):
    """Each head is rendered at rest and in its most displaced pose, in every view, with the
    options' chunk budget; the largest overflow is reported."""
    seen = []

    def render(vertices, faces, camera, chunk_budget):
        seen.append((float(np.asarray(vertices).max()), chunk_budget))
        return types.SimpleNamespace(overflow=int(np.asarray(vertices).max()))

    monkeypatch.setattr(f"{MODULE}.rasterise_hard", render)
    # a stand-in for the stacked views (one array leaf, one entry per view)
    monkeypatch.setattr(Supervision2DOptions, "cameras", lambda self: np.zeros(2))
    data = object.__new__(TrainingSet)
    displacements = np.zeros((2, 3, 4, 3))
    displacements[0, 1, 2, 0] = 5.0  # head 0: pose 1 moves most
    displacements[1, 2, 0, 1] = 7.0  # head 1: pose 2
    object.__setattr__(data, "vertices", np.zeros((2, 4, 3)))
    object.__setattr__(data, "displacements", displacements)
    opts = Supervision2DOptions(yaw_degrees=(0.0, 35.0), chunk_budget=4.0)
    faces = np.zeros((2, 1, 3), np.int32)  # only passed through to the stand-in
    assert chunk_overflow(data, faces, opts) == 7
    assert seen == [(x, 4.0) for x in (0, 0, 5, 5, 0, 0, 7, 7)]  # two views per state


def test_evaluate_2d_scores_each_model_beside_no_motion(monkeypatch):
    """A stand-in model that predicts half of every true displacement: half of no motion's
    error, an amplitude ratio of one half, on the ICT heads and on MakeHuman."""
    heads = [_head("test00/u", 1.0), _head("test01/u", 2.0)]
    truth = {id(h.vertices): h.displacements for h in heads}
    mh = types.SimpleNamespace(
        neutral=np.ones((4, 3)),
        faces=np.asarray([[0, 1, 2]], np.int32),
        names=("jawOpen", "eyeBlinkLeft", "tongueOut"),
        deltas=np.stack([np.full((4, 3), 0.1 * (i + 1)) for i in range(3)]),
        skin=np.asarray([True, True, True, False]),
    )
    truth[id(mh.neutral)] = np.concatenate([mh.deltas[:2], mh.deltas[:1] + mh.deltas[1:2]])

    def generate(model, poses, vertices, faces, operators=None):
        return types.SimpleNamespace(displacements=0.5 * truth[id(vertices)])

    monkeypatch.setattr(f"{MODULE}.generate_rig", generate)
    monkeypatch.setattr(f"{MODULE}.head_inputs", lambda v, f, k: (None, None, None, None))
    monkeypatch.setattr(f"{MODULE}.load_makehuman", lambda data_dir: mh)
    found = evaluate_2d({"half": _model()}, _dataset(test=heads))
    none, half = found["no_motion"], found["half"]
    for key in ("ict_unseen_mae_mm", "ict_unseen_q95_mm", "ict_unseen_single_expressions_mae_mm"):
        assert half[key] == pytest.approx(none[key] / 2) and none[key] > 0
    lengths = np.concatenate([np.linalg.norm(h.displacements, axis=-1).ravel() for h in heads])
    assert none["ict_unseen_mae_mm"] == pytest.approx(10 * lengths.mean())
    assert (none["ict_unseen_amplitude_ratio"], half["ict_unseen_amplitude_ratio"]) == (0, 0.5)
    assert half["makehuman_mae_mm"] == pytest.approx(none["makehuman_mae_mm"] / 2)
    assert half["makehuman_amplitude_ratio_median"] == pytest.approx(0.5)
    assert none["makehuman_amplitude_ratio_median"] == 0


@pytest.mark.slow  # a minute: compiles the soft and fast rasterisers at 256^2
def test_rasteriser_checks_on_the_ict_head(data_dir):
    found = rasteriser_checks(data_dir, quick=True)
    assert found["grad_rel_error"] < 0.02 and found["hard_vs_reference_iou"] > 0.99
    fast = found["fast_path"]
    assert fast["grad_rel_error_silhouette"] < 1e-3 and fast["grad_rel_error_interpolation"] < 1e-3
    assert fast["hard_vs_reference_iou"] > 0.99 and fast["overflow"] == 0
    assert found["fps_256"] > 0 and found["fps_256_soft"] > 0
