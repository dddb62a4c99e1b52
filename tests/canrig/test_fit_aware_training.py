"""Fit-aware fine-tuning: ``fitted_range`` (the evaluation's solver inside a training step)
and ``TrainOptions.fit_weight`` / ``init_from``."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import numpy as np
import pytest

from canrig_jax.canrig import (
    ExampleOptions,
    TrainOptions,
    build_training_set,
    fitted_range,
    influence_mask,
    load_model,
    sample_examples,
    split_capture,
    train,
)

TINY = ExampleOptions(batch=3, n_vertices=48, n_handles=(3, 12), handle_bucket=12)


@pytest.fixture(scope="module")
def tiny_data(ict_quartic, livelink_weights):
    capture_train, _ = split_capture(livelink_weights[:12])
    return build_training_set(ict_quartic, capture_train, n_random=6, n_pool=40, seed=0)


@pytest.fixture(scope="module")
def tiny_model(tiny_data, tmp_path_factory):
    path = tmp_path_factory.mktemp("fit") / "init.eqx"
    options = TrainOptions(steps=3, examples=TINY, interpolation_prior=True)
    train(tiny_data, options, checkpoint=path, progress=False)
    return path, options


def _leaves(model):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))]


def _pool_error(model, data, ex, displacements):
    """Per example, the mean Euclidean error (cm) over the handle pool's vertices of the
    forward pass with ``displacements``, written out from the model's call (numpy base
    shapes, not the library's ``_base_shape``)."""
    shapes, nearby, neutral = (np.asarray(a) for a in (data.shapes, data.nearby, data.neutral))
    pool = np.asarray(data.pool)
    errors = []
    for i in range(len(ex.target)):
        target = shapes[ex.target[i]]
        if ex.base_nearby[i] == 1:
            base = nearby[ex.target[i]]
        else:
            base = neutral if ex.base[i] < 0 else shapes[ex.base[i]]
        handles = pool[np.asarray(ex.handles[i])]
        distance = np.asarray(data.pool_distance)[pool][:, np.asarray(ex.handles[i])]
        n = len(handles)
        radius, falloff = np.full(n, ex.radius[i]), np.full(n, ex.falloff[i])
        mask = influence_mask(distance, radius, falloff, model.clamp) * ex.handle_valid[i][None, :]
        shape = model(
            model.encode_queries(neutral[pool]),
            base[pool],
            neutral[handles],
            base[handles],
            displacements[i],
            mask,
            0.0,
        )
        errors.append(float(np.linalg.norm(np.asarray(shape) - target[pool], axis=1).mean()))
    return np.array(errors)


def test_fitted_range_is_never_worse_than_the_direct_displacements(tiny_data, tiny_model):
    """On the pool's vertices (where it is solved) the fit is at most the direct pass's error,
    and lower on some; padding handles stay exactly zero."""
    model, _ = load_model(tiny_model[0], tiny_data.neutral)
    options = dataclasses.replace(TINY, batch=8)
    n_shapes, n_vertices = tiny_data.shapes.shape[:2]
    ex = sample_examples(np.random.default_rng(5), n_shapes, 40, n_vertices, options)
    fitted = np.asarray(fitted_range(model, tiny_data, ex, 0.0))
    valid = np.asarray(ex.handle_valid)
    assert np.all(fitted[valid == 0] == 0.0)
    shapes, nearby, neutral = (
        np.asarray(a) for a in (tiny_data.shapes, tiny_data.nearby, tiny_data.neutral)
    )
    pool = np.asarray(tiny_data.pool)
    direct = []
    for i in range(len(ex.target)):
        if ex.base_nearby[i] == 1:
            base = nearby[ex.target[i]]
        else:
            base = neutral if ex.base[i] < 0 else shapes[ex.base[i]]
        h = pool[np.asarray(ex.handles[i])]
        direct.append((shapes[ex.target[i]][h] - base[h]) * valid[i][:, None])
    direct_error = _pool_error(model, tiny_data, ex, np.stack(direct))
    fitted_error = _pool_error(model, tiny_data, ex, fitted)
    assert np.all(fitted_error <= direct_error * (1 + 1e-5) + 1e-7)
    assert np.any(fitted_error < 0.99 * direct_error)  # and it does move some


def test_fine_tune_starts_from_its_checkpoint_and_resumes_exactly(tiny_data, tiny_model, tmp_path):
    init, base_options = tiny_model
    start, _ = load_model(init, tiny_data.neutral)
    options = dataclasses.replace(
        base_options, steps=0, init_from=str(init), fit_weight=1.0, learning_rate=1e-4
    )
    none = train(tiny_data, options, checkpoint=tmp_path / "z.eqx", progress=False)
    for a, b in zip(_leaves(start), _leaves(none.model), strict=True):
        np.testing.assert_array_equal(a, b)
    options = dataclasses.replace(options, steps=3, log_every=1, checkpoint_every=1)
    whole = train(tiny_data, options, checkpoint=tmp_path / "a.eqx", progress=False)
    assert all("fitted_error_mm" in h for h in whole.history)
    assert any(
        not np.array_equal(a, b) for a, b in zip(_leaves(start), _leaves(whole.model), strict=True)
    )
    train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False, stop_after=2)
    resumed = train(tiny_data, options, checkpoint=tmp_path / "b.eqx", progress=False)
    for a, b in zip(_leaves(whole.model), _leaves(resumed.model), strict=True):
        np.testing.assert_array_equal(a, b)


def test_fine_tune_refuses_another_architecture_or_a_missing_checkpoint(
    tiny_data, tiny_model, tmp_path
):
    init, base_options = tiny_model
    wider = dataclasses.replace(base_options, init_from=str(init), width=32)
    with pytest.raises(ValueError, match="^init_from:.*width"):
        train(tiny_data, wider, progress=False)
    missing = dataclasses.replace(base_options, init_from=str(tmp_path / "none.eqx"))
    with pytest.raises(ValueError, match="^init_from: no checkpoint"):
        train(tiny_data, missing, progress=False)
    with pytest.raises(ValueError, match="fit_weight"):
        TrainOptions(fit_weight=-1.0)
