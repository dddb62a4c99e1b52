"""Bad inputs of CANRig's public checked entry points: influence masks, handle parameters,
the correlation prior and the training options. (``influence_mask`` stays jit-safe: traced
arguments are not checked, so the jitted forward pass is unaffected.)"""

from __future__ import annotations

import types

import jax
import numpy as np
import pytest

from canrig_jax.canrig import TrainOptions, correlation_edge_factor, influence_mask
from canrig_jax.canrig._data import DataOptions, capture_mixes_of
from canrig_jax.canrig._masks import check_handle_parameters
from canrig_jax.data import load_mediapipe_face

from .conftest import handled, raises, run_case

DISTANCE = np.array([[0.0, 1.0], [2.0, np.inf], [0.5, 3.0]], np.float32)
RADIUS = np.array([1.0, 2.0], np.float32)
FALLOFF = np.array([3.0, 3.0], np.float32)


def _mask_reference(distance, radius, falloff):
    with np.errstate(invalid="ignore"):
        out = 0.5 * (1.0 - np.tanh(falloff * (distance - radius)))
    return np.where(np.isinf(distance), 0.0, out)


@pytest.fixture(scope="module")
def ctx(data_dir):
    face = load_mediapipe_face(data_dir)
    rng = np.random.default_rng(0)
    shapes = face.neutral[None] + rng.normal(0, 0.1, (4,) + face.neutral.shape)
    return types.SimpleNamespace(faces=face.faces, shapes=shapes.astype(np.float32))


INFLUENCE_MASK = [
    raises(
        "negative-radius",
        lambda c: influence_mask(DISTANCE, -RADIUS, FALLOFF),
        ValueError,
        "radius",
    ),
    raises(
        "zero-radius", lambda c: influence_mask(DISTANCE, 0 * RADIUS, FALLOFF), ValueError, "radius"
    ),
    raises(
        "nan-radius",
        lambda c: influence_mask(DISTANCE, [np.nan, 1.0], FALLOFF),
        ValueError,
        "radius",
    ),
    raises(
        "negative-falloff",
        lambda c: influence_mask(DISTANCE, RADIUS, -FALLOFF),
        ValueError,
        "falloff",
    ),
    raises(
        "inf-falloff",
        lambda c: influence_mask(DISTANCE, RADIUS, [np.inf, 1.0]),
        ValueError,
        "falloff",
    ),
    raises(
        "nan-distance",
        lambda c: influence_mask(np.where(DISTANCE == 2.0, np.nan, DISTANCE), RADIUS, FALLOFF),
        ValueError,
        "distance",
    ),
    raises(
        "negative-distance",
        lambda c: influence_mask(-DISTANCE, RADIUS, FALLOFF),
        ValueError,
        "distance",
    ),
    raises(
        "complex-distance",
        lambda c: influence_mask(DISTANCE + 1j, RADIUS, FALLOFF),
        TypeError,
        "distance",
    ),
    raises(
        "clamp-one",
        lambda c: influence_mask(DISTANCE, RADIUS, FALLOFF, clamp=1.0),
        ValueError,
        "clamp",
    ),
    handled(
        "unreachable-is-zero",
        lambda c: influence_mask(DISTANCE, RADIUS, FALLOFF),
        lambda m, c: np.testing.assert_allclose(
            m, _mask_reference(DISTANCE, RADIUS, FALLOFF), atol=1e-6
        ),
    ),
    handled(
        "traced-arguments-not-checked",
        lambda c: jax.jit(influence_mask)(DISTANCE, RADIUS, FALLOFF),
        lambda m, c: np.testing.assert_allclose(
            m, _mask_reference(DISTANCE, RADIUS, FALLOFF), atol=1e-6
        ),
    ),
    handled(
        "integer-distances",
        lambda c: influence_mask(np.array([[0, 3]]), RADIUS, FALLOFF),
        lambda m, c: np.testing.assert_allclose(
            m, _mask_reference(np.array([[0.0, 3.0]]), RADIUS, FALLOFF), atol=1e-6
        ),
    ),
]


@pytest.mark.parametrize("case", INFLUENCE_MASK)
def test_influence_mask(case, ctx):
    run_case(case, ctx)


HANDLE_PARAMETERS = [
    raises(
        "negative-radius", lambda c: check_handle_parameters(-1.0, 3.0, 2), ValueError, "radius"
    ),
    raises(
        "negative-falloff", lambda c: check_handle_parameters(1.0, -3.0, 2), ValueError, "falloff"
    ),
    raises(
        "radius-per-handle-count",
        lambda c: check_handle_parameters([1.0, 2.0, 3.0], 3.0, 2),
        ValueError,
        "radius",
    ),
    raises("complex-radius", lambda c: check_handle_parameters(1j, 3.0, 2), TypeError, "radius"),
    raises("string-falloff", lambda c: check_handle_parameters(1.0, "3", 2), TypeError, "falloff"),
    handled(
        "scalars-broadcast",
        lambda c: check_handle_parameters(2, 3.0, 3),
        lambda out, c: (
            np.testing.assert_array_equal(out[0], [2, 2, 2]),
            np.testing.assert_array_equal(out[1], [3, 3, 3]),
        ),
    ),
]


@pytest.mark.parametrize("case", HANDLE_PARAMETERS)
def test_check_handle_parameters(case, ctx):
    run_case(case, ctx)


CORRELATION_PRIOR = [
    raises(
        "nan-shape",
        lambda c: correlation_edge_factor(c.faces, np.where(c.shapes > 5, np.nan, c.shapes)),
        ValueError,
        "shapes",
    ),
    raises(
        "one-shape", lambda c: correlation_edge_factor(c.faces, c.shapes[:1]), ValueError, "shapes"
    ),
    raises(
        "complex-shapes",
        lambda c: correlation_edge_factor(c.faces, c.shapes + 1j),
        TypeError,
        "shapes",
    ),
    raises(
        "faces-beyond-shapes",
        lambda c: correlation_edge_factor(c.faces, c.shapes[:, :100]),
        ValueError,
        "faces",
    ),
    raises(
        "float-faces",
        lambda c: correlation_edge_factor(c.faces + 0.5, c.shapes),
        ValueError,
        "faces",
    ),
    handled(
        "constant-vertex-is-uncorrelated",
        lambda c: correlation_edge_factor(
            c.faces, np.where(np.arange(468)[None, :, None] == 0, 0.0, c.shapes)
        ),
        lambda f, c: np.all((f > 0) & (f <= 1)) or pytest.fail("factor outside (0, 1]"),
    ),
]


@pytest.mark.parametrize("case", CORRELATION_PRIOR)
def test_correlation_edge_factor(case, ctx):
    run_case(case, ctx)


OPTIONS = [
    raises("variant", lambda c: TrainOptions(variant="big"), ValueError, "variant"),
    raises("loss", lambda c: TrainOptions(loss="l1"), ValueError, "loss"),
    raises("learning-rate", lambda c: TrainOptions(learning_rate=0.0), ValueError, "learning_rate"),
    raises("steps", lambda c: TrainOptions(steps=-1), ValueError, "steps"),
    raises("decay-floor", lambda c: TrainOptions(decay_floor=2.0), ValueError, "decay_floor"),
    raises(
        "farthest-metric",
        lambda c: DataOptions(farthest_metric="manhattan"),
        ValueError,
        "farthest_metric",
    ),
    raises("n-random", lambda c: DataOptions(n_random=-1), ValueError, "n_random"),
    raises("n-active", lambda c: DataOptions(n_active=(5, 2)), ValueError, "n_active"),
    raises(
        "distance-limit",
        lambda c: DataOptions(distance_limit_cm=0.0),
        ValueError,
        "distance_limit_cm",
    ),
    raises(
        "capture-mixes-of-one-frame",
        lambda c: capture_mixes_of(np.zeros((1, 3)), 2, np.random.default_rng(0)),
        ValueError,
        "capture",
    ),
]


@pytest.mark.parametrize("case", OPTIONS)
def test_training_options(case, ctx):
    run_case(case, ctx)
