"""The RigAnyFace training recipes: each model's options from the shared command line (the
standard run and a one-model training must build the same options, or a checkpoint would not
resume), its base, its training set and the record of a checkpoint."""

from __future__ import annotations

import argparse
import dataclasses

import equinox as eqx
import jax
import numpy as np
import pytest

from canrig_jax.autorig import DEFAULT_CHECKPOINT, RigAnyFaceTrainOptions, load_riganyface
from canrig_jax.autorig._data import AutorigDataset, PoseSet, RiggedHead
from canrig_jax.autorig._train import TrainingSet
from canrig_jax.data import ICTFaceModel
from canrig_jax.papers.riganyface import (
    ANCHOR_CM,
    ANCHORED_RESIDUAL_MODELS,
    PURE_MODELS,
    RAF_LOSSES,
    RECIPE_MODELS,
    RESIDUAL_MODEL,
    add_recipe_arguments,
    checkpoint_record,
    recipe_base,
    recipe_options,
    recipe_training_set,
)

MODULE = "canrig_jax.papers.riganyface._recipes"


def _args(*argv: str) -> argparse.Namespace:
    return add_recipe_arguments(argparse.ArgumentParser()).parse_args(list(argv))


def test_pure_models_take_the_loss_and_size_and_differ_only_in_the_global_encoder():
    args = _args("--raf-loss", "euclidean_static", "--raf-width", "64", "--steps", "700")
    raf = recipe_options(args, "raf")
    ablation = recipe_options(args, "raf_no_global_encoder")
    assert (raf.loss, raf.static_weight, raf.width, raf.steps) == ("euclidean", 1.0, 64, 700)
    assert ablation.global_size == 0 and raf.global_size == RigAnyFaceTrainOptions.global_size
    assert dataclasses.replace(ablation, global_size=raf.global_size) == raf
    assert not raf.residual and raf.warmup_steps == 200 and raf.checkpoint_every == 200
    for loss, fields in RAF_LOSSES.items():
        options = recipe_options(_args("--raf-loss", loss), "raf")
        assert {k: getattr(options, k) for k in fields} == fields


def test_residual_models_have_their_own_schedule_and_no_clock():
    args = _args("--minutes", "30", "--residual-steps", "2500", "--residual-gate", "5e-5")
    base = recipe_options(args)
    assert base.max_minutes == 30 and not base.residual  # what results.json's config records
    for name in (RESIDUAL_MODEL, *ANCHORED_RESIDUAL_MODELS):
        options = recipe_options(args, name)
        assert options.residual and options.loss == "euclidean" and options.static_weight == 1
        assert (options.steps, options.warmup_steps, options.max_minutes) == (2500, 200, None)
        assert options.residual_gate == 5e-5
    short = recipe_options(_args("--residual-steps", "500"), RESIDUAL_MODEL)
    assert short.warmup_steps == 50  # a tenth of a short schedule


def test_quick_runs_are_tiny_whatever_the_budget():
    args = _args("--quick", "--steps", "9000", "--minutes", "60", "--residual-steps", "9000")
    for name in RECIPE_MODELS:
        options = recipe_options(args, name)
        assert (options.steps, options.warmup_steps, options.max_minutes) == (20, 5, None)
        assert options.checkpoint_every == 10


def test_an_unknown_model_is_named():
    with pytest.raises(ValueError, match="name: expected one of"):
        recipe_options(_args(), "raf_wide")
    with pytest.raises(ValueError, match="name: expected one of"):
        recipe_base("raf_wide")


def test_each_model_has_its_base():
    assert [recipe_base(name) for name in PURE_MODELS] == [None, None]
    assert recipe_base(RESIDUAL_MODEL) == "deformation_transfer"
    assert recipe_base("raf_anchored_dt_residual") == "deformation_transfer_anchored"
    assert recipe_base("raf_anchored_part_dt_residual") == "deformation_transfer_anchored_part"


@pytest.mark.parametrize(
    "name, static_below, anchor",
    [
        ("raf", None, None),
        (RESIDUAL_MODEL, None, "vertex"),
        ("raf_anchored_dt_residual", ANCHOR_CM, "vertex"),
        ("raf_anchored_skin_vertex_dt_residual", ANCHOR_CM, "skin_vertex"),
    ],
)
def test_the_training_set_carries_each_residual_models_base(
    monkeypatch, name, static_below, anchor
):
    """A pure model trains on the heads alone; a residual one on each head's transfer (plain
    or anchored per its mode), read through the cache with the run's seed."""
    transfers, sets = [], []

    def transfer(dataset, head, cache, seed, below=None, *, anchor="vertex"):
        transfers.append((head, cache, seed, below, anchor))
        return np.full((2, 3, 3), len(transfers), np.float32)

    made = object.__new__(TrainingSet)  # a stand-in of the right type

    def training(heads, poses, *, k, progress, base=None):
        sets.append((heads, k, base))
        return made

    monkeypatch.setattr(f"{MODULE}.cached_transfer", transfer)
    monkeypatch.setattr(f"{MODULE}.training_set", training)
    dataset = _dataset()
    found = recipe_training_set(dataset, name, k=64, cache="cache", seed=3, progress=False)
    assert found is made and sets[0][0] is dataset.train and sets[0][1] == 64
    if anchor is None:
        assert transfers == [] and sets[0][2] is None
    else:
        assert transfers == [(h, "cache", 3, static_below, anchor) for h in dataset.train]
        assert [float(b[0, 0, 0]) for b in sets[0][2]] == [1, 2]


def _dataset() -> AutorigDataset:
    """Two training heads (a triangle each) and a one-triangle ICT stand-in."""
    triangle = np.asarray([[0, 1, 2]], np.int32)
    ict = ICTFaceModel(
        neutral=np.eye(3, dtype=np.float32),
        faces=triangle,
        deltas=np.zeros((1, 3, 3), np.float32),
        names=("jawOpen",),
        part_names=("Face",),
        part_vertex_range=np.asarray([[0, 3]], np.int32),
        component_labels=np.zeros(3, np.int32),
        landmarks=np.zeros(68, np.int32),
        vertex_ids=np.arange(3, dtype=np.int32),
    )
    heads = [
        RiggedHead(
            f"train0{i}/t",
            np.eye(3),
            triangle,
            np.zeros((1, 3, 3)),
            np.zeros(68, int),
            np.zeros(3, np.int32),
            np.zeros(2),
            "t",
        )  # fmt: skip
        for i in range(2)
    ]
    poses = PoseSet(("jawOpen",), ((0,),))
    return AutorigDataset(poses, ict, np.zeros((1, 3, 3)), heads, {})


def test_checkpoint_record_reads_the_header():
    model, _, header = load_riganyface(DEFAULT_CHECKPOINT)
    record = checkpoint_record(model, header)
    leaves = jax.tree.leaves(eqx.filter(model, eqx.is_array))
    assert record["parameters"] == sum(x.size for x in leaves) > 0
    assert record["steps"] == header["step"] and record["minutes"] == header["seconds"] / 60
    assert record["final_train_error_mm"] == header["history"][-1]["error_mm"]
    assert RigAnyFaceTrainOptions(**record["options"]).width == 64  # the default model's
