"""Training: the loss goes down on real shapes, checkpoints are atomic and resuming an
interrupted run gives exactly the uninterrupted result; example sampling."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import ExampleOptions, TrainOptions, build_training_set, load_model, train
from canrig_jax.canrig._data import DataOptions, capture_mixes_of, sample_examples
from canrig_jax.canrig._train import (
    EUCLIDEAN_SOFTNESS_MM,
    make_optimiser,
    read_checkpoint_state,
    vertex_penalty,
)
from canrig_jax.papers.canrig import add_training_options, split_capture, training_options_from_args

ROOT = Path(__file__).resolve().parents[2]

TINY = ExampleOptions(batch=2, n_vertices=48, n_handles=(3, 12), handle_bucket=12)


@pytest.fixture(scope="module")
def tiny_data(ict_quartic, livelink_weights):
    capture_train, _ = split_capture(livelink_weights[:12])
    return build_training_set(ict_quartic, capture_train, n_random=6, n_pool=40, seed=0)


def _leaves(model):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))]


def test_resumed_training_equals_uninterrupted(tiny_data, tmp_path):
    options = TrainOptions(steps=4, checkpoint_every=2, log_every=1, examples=TINY)
    whole = train(tiny_data, options, checkpoint=tmp_path / "a.eqx", progress=False)
    first = train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False, stop_after=3)
    assert first.step == 3  # stopped early (checkpoint at step 3), then resumed
    resumed = train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False)
    assert resumed.step == whole.step == 4
    for a, b in zip(_leaves(whole.model), _leaves(resumed.model), strict=True):
        np.testing.assert_array_equal(a, b)
    assert resumed.history == whole.history
    # the checkpoint loads back into the same model, options from its header
    loaded, state = load_model(tmp_path / "b.eqx", tiny_data.neutral)
    assert state["step"] == 4
    for a, b in zip(_leaves(whole.model), _leaves(loaded), strict=True):
        np.testing.assert_array_equal(a, b)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_checkpoint_with_other_options_is_refused(tiny_data, tmp_path):
    options = TrainOptions(steps=1, examples=TINY)
    train(tiny_data, options, checkpoint=tmp_path / "c.eqx", progress=False)
    with pytest.raises(ValueError, match="checkpoint"):
        train(
            tiny_data,
            dataclasses.replace(options, learning_rate=1e-2),
            checkpoint=tmp_path / "c.eqx",
            progress=False,
        )
    with pytest.raises(ValueError, match="path"):
        load_model(tmp_path / "missing.eqx", tiny_data.neutral)


def test_sampled_examples_respect_the_options():
    options = ExampleOptions(batch=64, n_vertices=30, n_handles=(20, 60), handle_bucket=25)
    ex = sample_examples(np.random.default_rng(0), 10, 100, 500, options)
    counts = np.asarray(ex.handle_valid).sum(axis=1)
    assert counts.min() >= 20 and counts.max() <= 60
    assert ex.handles.shape[1] % 25 == 0 or ex.handles.shape[1] == 60
    for row, count in zip(np.asarray(ex.handles), counts.astype(int), strict=True):
        assert len(set(row[:count].tolist())) == count  # distinct handles
    assert np.all(ex.target != ex.base)  # "another" pose, or -1 for the neutral
    assert np.all((ex.radius >= 0.7) & (ex.radius <= 6.0))
    nearby, neutral = np.asarray(ex.base_nearby) == 1, np.asarray(ex.base) < 0
    assert 0 < nearby.sum() < 20 and 0 < neutral.sum() < 20 and not np.any(nearby & neutral)
    with pytest.raises(ValueError, match="n_handles"):
        sample_examples(np.random.default_rng(0), 10, 10, 500, options)


def test_evaluation_matched_sampling():
    """Farthest-point handle sets (prefixes), the evaluation radii/falloff and capture targets
    with the given probabilities; with these options off, the draws are the default ones."""
    sets = np.stack([np.arange(60)[::-1], np.arange(60)]).astype(np.int32)
    base = ExampleOptions(batch=256, n_vertices=10, n_handles=(20, 60), handle_bucket=20)
    plain = sample_examples(np.random.default_rng(3), 50, 100, 500, base)
    again = sample_examples(np.random.default_rng(3), 50, 100, 500, base, handle_sets=sets)
    leaves = jax.tree_util.tree_leaves
    for a, b in zip(leaves(plain), leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    options = dataclasses.replace(base, p_farthest=0.5, p_eval_radius=0.5, p_capture=0.25)
    ex = sample_examples(
        np.random.default_rng(3), 50, 100, 500, options, handle_sets=sets, n_capture=10
    )
    handles, valid = np.asarray(ex.handles), np.asarray(ex.handle_valid)
    farthest = 0
    for row, count in zip(handles, valid.sum(axis=1).astype(int), strict=True):
        assert len(set(row[:count].tolist())) == count
        farthest += any(np.array_equal(row[:count], s[:count]) for s in sets)
    assert 80 < farthest < 180
    at_eval = np.isin(ex.radius, [1.0, 2.0, 4.0]) & (np.asarray(ex.falloff) == 3.0)
    assert 80 < at_eval.sum() < 180
    from_capture = np.asarray(ex.target) < 10
    assert 30 < from_capture.sum() < 100
    target, base_index = np.asarray(ex.target), np.asarray(ex.base)
    assert np.all(target != base_index)
    with pytest.raises(ValueError, match="p_farthest"):
        sample_examples(np.random.default_rng(0), 50, 100, 500, options)


@pytest.mark.slow
def test_resume_with_schedule_and_options(tiny_data, tmp_path):
    """The learning-rate schedule and the model options survive a checkpoint round trip."""
    options = TrainOptions(
        steps=3,
        checkpoint_every=1,
        log_every=1,
        fourier=2,
        query_modulation=True,
        decay_steps=3,
        examples=TINY,
    )
    whole = train(tiny_data, options, checkpoint=tmp_path / "a.eqx", progress=False)
    train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False, stop_after=2)
    resumed = train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False)
    for a, b in zip(_leaves(whole.model), _leaves(resumed.model), strict=True):
        np.testing.assert_array_equal(a, b)
    loaded, state = load_model(tmp_path / "b.eqx", tiny_data.neutral)
    assert state["options"]["fourier"] == 2 and loaded.query_modulation is not None


def test_learning_rate_schedule_constant_then_cosine():
    """With a constant unit gradient Adam's bias-corrected step is exactly the learning rate,
    so the updates read back the schedule: constant until ``decay_start``, then a cosine down
    to ``decay_floor`` x the rate over ``decay_steps`` steps, then flat (closed form here)."""
    options = TrainOptions(decay_steps=20, decay_start=10, decay_floor=0.1)
    optimiser = make_optimiser(options)
    params = {"w": jnp.zeros(())}
    state = optimiser.init(params)
    rates = []
    for _ in range(40):
        updates, state = optimiser.update({"w": jnp.ones(())}, state, params)
        rates.append(-float(updates["w"]))
    t = np.clip(np.arange(40) - 10, 0, 20)
    expected = 1e-3 * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * t / 20)))
    np.testing.assert_allclose(rates, expected, rtol=1e-4)


@pytest.mark.parametrize(
    "bad", [{"decay_steps": -1}, {"decay_start": -5}, {"decay_floor": 1.5}, {"loss": "l1"}]
)
def test_bad_training_options_raise(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        TrainOptions(**bad)


def test_vertex_penalties_against_numpy():
    """Squared error in mm^2 (eq. 3) and the smoothed Euclidean error in mm, from cm
    differences; the Euclidean one has a finite gradient (zero) at a zero difference."""
    difference = np.random.default_rng(0).normal(scale=0.05, size=(50, 3)).astype(np.float32)
    squared = (difference**2).sum(axis=1) * 100.0
    np.testing.assert_allclose(vertex_penalty(difference, "squared"), squared.mean(), rtol=1e-5)
    euclidean = np.sqrt(squared + EUCLIDEAN_SOFTNESS_MM**2).mean()
    np.testing.assert_allclose(vertex_penalty(difference, "euclidean"), euclidean, rtol=1e-5)
    gradient = jax.grad(lambda d: vertex_penalty(d, "euclidean"))(jnp.zeros((4, 3)))
    np.testing.assert_array_equal(gradient, 0.0)


def test_capture_mixes_lie_between_two_training_frames(livelink_weights):
    """Each mix is (1 - t) w_a + t w_b of two distinct training frames with t in [0, 1]."""
    capture_train, _ = split_capture(livelink_weights)
    mixes = capture_mixes_of(capture_train, 50, np.random.default_rng(0))
    assert mixes.shape == (50, capture_train.shape[1])
    found = 0
    for mix in mixes:
        for a in range(len(capture_train)):
            for b in range(len(capture_train)):
                step = capture_train[b] - capture_train[a]
                if a == b or not np.any(step):
                    continue
                t = float(step @ (mix - capture_train[a]) / (step @ step))
                if -1e-6 <= t <= 1 + 1e-6 and np.allclose(
                    capture_train[a] + t * step, mix, atol=1e-5
                ):
                    found += 1
                    break
            else:
                continue
            break
    assert found == len(mixes)
    with pytest.raises(ValueError, match="capture"):
        capture_mixes_of(capture_train[:1], 3, np.random.default_rng(0))


def test_training_set_appends_capture_mixes(ict_quartic, livelink_weights):
    """Mixes are appended after the unchanged capture and random shapes."""
    capture_train, _ = split_capture(livelink_weights[:12])
    plain = build_training_set(ict_quartic, capture_train, n_random=6, n_pool=40, seed=0)
    mixed = build_training_set(
        ict_quartic, capture_train, n_random=6, n_pool=40, seed=0, capture_mixes=4
    )
    n = plain.shapes.shape[0]
    assert mixed.shapes.shape[0] == mixed.nearby.shape[0] == n + 4
    np.testing.assert_array_equal(mixed.shapes[:n], plain.shapes)
    np.testing.assert_array_equal(mixed.nearby[:n], plain.nearby)
    np.testing.assert_array_equal(mixed.pool, plain.pool)
    with pytest.raises(ValueError, match="capture_mixes"):
        build_training_set(ict_quartic, capture_train, n_random=6, capture_mixes=-1)


def test_checkpoint_stores_data_options_and_refuses_other_ones(tiny_data, tmp_path):
    options = TrainOptions(steps=1, examples=TINY)
    built = {**DataOptions(n_random=6, n_pool=40).to_dict(), "seed": 0}
    path = tmp_path / "d.eqx"
    train(tiny_data, options, checkpoint=path, progress=False, data_options=built)
    assert read_checkpoint_state(path)["data_options"] == built
    # same data options (the budget extended): resumes
    more = dataclasses.replace(options, steps=2)
    assert train(tiny_data, more, checkpoint=path, progress=False, data_options=built).step == 2
    with pytest.raises(ValueError, match="^checkpoint:.*data options.*farthest_sets"):
        train(
            tiny_data,
            more,
            checkpoint=path,
            progress=False,
            data_options={**built, "farthest_sets": 4},
        )


def test_checkpoint_without_data_options_still_resumes(tiny_data, tmp_path):
    """Checkpoints written before data options were stored (and without an integrity hash)
    keep loading and resuming."""
    options = TrainOptions(steps=1, examples=TINY)
    path = tmp_path / "old.eqx"
    train(tiny_data, options, checkpoint=path, progress=False)
    lines = path.read_bytes().split(b"\n", 1)
    header = json.loads(lines[0])
    del header["sha256"], header["data_options"]
    path.write_bytes(json.dumps(header).encode() + b"\n" + lines[1])
    model, state = load_model(path, tiny_data.neutral)
    assert state["step"] == 1 and "data_options" not in state
    data_options = {**DataOptions().to_dict(), "seed": 0}
    result = train(
        tiny_data,
        dataclasses.replace(options, steps=2),
        checkpoint=path,
        progress=False,
        data_options=data_options,
    )
    assert result.step == 2
    assert read_checkpoint_state(path)["data_options"] == data_options


def test_committed_checkpoints_load():
    """The committed standard checkpoint (written before the integrity hash) still loads."""
    path = ROOT / "experiments" / "results" / "canrig" / "checkpoint.eqx"
    state = read_checkpoint_state(path)
    assert state["step"] > 0 and TrainOptions.from_dict(state["options"]).width == 96


def test_training_command_line_is_derived_from_the_options():
    """Every field of TrainOptions, ExampleOptions and DataOptions is an option of the
    training command line, and a non-default value of each round-trips through it."""

    def parse(argv):
        return add_training_options(argparse.ArgumentParser()).parse_args(argv)

    options = TrainOptions(
        variant="canrig",
        n_heads=2,
        latent=32,
        width=48,
        n_layers=2,
        fourier=3,
        linear_skip=True,
        interpolation_prior=True,
        learning_rate=3e-4,
        decay_steps=9,
        decay_floor=0.1,
        decay_start=2,
        steps=77,
        max_minutes=3.5,
        beta=0.5,
        sp_weight=0.25,
        loss="euclidean",
        seed=5,
        checkpoint_every=7,
        log_every=3,
        examples=ExampleOptions(
            batch=3,
            n_vertices=20,
            n_handles=(2, 9),
            p_capture=0.4,
            eval_radii_cm=(1.5, 3.0),
            p_farthest=0.2,
        ),
    )
    data_options = DataOptions(n_random=9, n_active=(2, 3), farthest_metric="geodesic")
    parsed = parse([*_flags(options), *_flags(data_options)])
    assert training_options_from_args(parsed) == (options, data_options)
    # the committed command's short flags still work
    got, _ = training_options_from_args(parse(["--heads", "2", "--minutes", "9"]))
    assert (got.n_heads, got.max_minutes, got.steps) == (2, 9.0, 100_000)
    # --quick: the step budget, no time limit, and the tiny data set
    got, data = training_options_from_args(parse(_flags(options)), quick=True)
    assert (got.steps, got.max_minutes, got.width) == (30, None, options.width)
    assert data == DataOptions().quick()


def _flags(instance) -> list[str]:
    out = []
    for field in dataclasses.fields(instance):
        value = getattr(instance, field.name)
        if dataclasses.is_dataclass(value):
            out += _flags(value)
            continue
        flag = "--" + field.name.replace("_", "-")
        if isinstance(value, bool):
            out.append(flag if value else "--no-" + flag[2:])
        elif value is None:
            continue
        elif isinstance(value, tuple):
            out += [flag, *map(str, value)]
        else:
            out += [flag, str(value)]
    return out
