"""Bad inputs of pose space editing: fits (widths that no longer reproduce the edits), fix
shapes with a broken sculpt, application to bad poses, layers, the few-edits width rule,
temporal change and edit reuse."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest

from canrig_jax.rig import evaluate_batch
from canrig_jax.wpse import (
    apply,
    fit_layered,
    fit_pose_space_edit,
    fit_width,
    fix_shape_rig,
    prepare_edits,
    reuse_edits,
    sigma_from_gui,
    temporal_change,
)

from .conftest import handled, raises, run_case

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "wpse"))
from conftest import grid_rig  # noqa: E402  (the WPSE tests' tiny rig)


@pytest.fixture(scope="module")
def ctx():
    rig = grid_rig()
    rng = np.random.default_rng(1)
    poses = rng.uniform(0, 1, (12, rig.n_blendshapes)).astype(np.float32)
    edits = 0.5 * np.tensordot(np.sin(2.0 * poses) ** 2, np.asarray(rig.deltas), 1)
    model = fit_pose_space_edit(rig, poses, edits.astype(np.float32), sigma=0.4)
    return types.SimpleNamespace(rig=rig, poses=poses, edits=edits.astype(np.float32), model=model)


def _fit(c, **kw):
    args = dict(sigma=0.4)
    args.update(kw)
    return fit_pose_space_edit(c.rig, c.poses, c.edits, **args)


def _reproduces(model, c):
    """The edit is reproduced at its own poses (the interpolation property)."""
    posed = np.asarray(evaluate_batch(c.rig, c.poses))
    got = np.stack([np.asarray(apply(model, p, m)) for p, m in zip(c.poses, posed, strict=True)])
    np.testing.assert_allclose(got - posed, c.edits, atol=1e-3 * np.abs(c.edits).max())


FIT = [
    # found by the fit itself (the solve misses its own data): compiles before the error
    raises(
        "pse-sigma-20",
        lambda c: _fit(c, sigma=20.0, metric="euclidean"),
        ValueError,
        "sigma",
        compiles=True,
    ),
    # found by the fit itself (the solve misses its own data): compiles before the error
    raises("wpse-sigma-20", lambda c: _fit(c, sigma=20.0), ValueError, "sigma", compiles=True),
    # found by the fit itself (the solve misses its own data): compiles before the error
    raises(
        "pse-sigma-1e6",
        lambda c: _fit(c, sigma=1e6, metric="euclidean"),
        ValueError,
        "sigma",
        compiles=True,
    ),
    # found by the fit itself (the solve misses its own data): compiles before the error
    raises("wpse-sigma-1e6", lambda c: _fit(c, sigma=1e6), ValueError, "sigma", compiles=True),
    raises("negative-sigma", lambda c: _fit(c, sigma=-0.4), ValueError, "sigma"),
    raises("nan-sigma", lambda c: _fit(c, sigma=np.nan), ValueError, "sigma"),
    raises("sigma-vector", lambda c: _fit(c, sigma=[0.4, 0.4]), ValueError, "sigma"),
    raises(
        "nan-pose",
        lambda c: fit_pose_space_edit(
            c.rig, np.where(c.poses > 0.9, np.nan, c.poses), c.edits, sigma=0.4
        ),
        ValueError,
        "poses",
    ),
    raises(
        "nan-edit",
        lambda c: fit_pose_space_edit(
            c.rig, c.poses, np.where(c.edits > 0.01, np.nan, c.edits), sigma=0.4
        ),
        ValueError,
        "edits",
    ),
    raises(
        "edits-shape",
        lambda c: fit_pose_space_edit(c.rig, c.poses, c.edits[:, :-1], sigma=0.4),
        ValueError,
        "edits",
    ),
    raises(
        "poses-width",
        lambda c: fit_pose_space_edit(c.rig, c.poses[:, :-1], c.edits, sigma=0.4),
        ValueError,
        "poses",
    ),
    raises(
        "duplicate-poses",
        lambda c: fit_pose_space_edit(c.rig, c.poses[[0, 0]], c.edits[[0, 1]], sigma=0.4),
        ValueError,
        "poses",
    ),
    raises("metric-name", lambda c: _fit(c, metric="cosine"), ValueError, "metric"),
    raises("negative-ridge", lambda c: _fit(c, ridge=-1.0), ValueError, "ridge"),
    raises(
        "not-a-rig",
        lambda c: fit_pose_space_edit(c.poses, c.poses, c.edits, sigma=0.4),
        ValueError,
        "rig",
    ),
    handled("working-width-reproduces", lambda c: _fit(c, sigma=0.4), _reproduces),
    handled(
        "pse-working-width-reproduces",
        lambda c: _fit(c, sigma=0.4, metric="euclidean"),
        _reproduces,
    ),
]


@pytest.mark.parametrize("case", FIT)
def test_fit_pose_space_edit(case, ctx):
    run_case(case, ctx)


def _sculpt_nan(corners):
    out = np.zeros((len(corners), 49, 3), np.float32)
    out[0, 3] = np.nan
    return out


FIX_SHAPE_RIG = [
    raises(
        "nan-sculpt", lambda c: fix_shape_rig(c.rig, [[0, 1]], _sculpt_nan), ValueError, "sculpt"
    ),
    raises(
        "complex-sculpt",
        lambda c: fix_shape_rig(c.rig, [[0, 1]], lambda w: np.zeros((1, 49, 3), complex)),
        TypeError,
        "sculpt",
    ),
    raises(
        "sculpt-shape",
        lambda c: fix_shape_rig(c.rig, [[0, 1]], lambda w: np.zeros((1, 48, 3))),
        ValueError,
        "sculpt",
    ),
    raises(
        "sculpt-not-callable",
        lambda c: fix_shape_rig(c.rig, [[0, 1]], np.zeros((1, 49, 3))),
        TypeError,
        "sculpt",
    ),
    raises(
        "trigger-out-of-range",
        lambda c: fix_shape_rig(c.rig, [[0, 9]], lambda w: np.zeros((1, 49, 3))),
        ValueError,
        "triggers",
    ),
    raises(
        "float-triggers",
        lambda c: fix_shape_rig(c.rig, [[0.0, 1.5]], lambda w: np.zeros((1, 49, 3))),
        TypeError,
        "triggers",
    ),
    raises(
        "one-shape-trigger",
        lambda c: fix_shape_rig(c.rig, [[0]], lambda w: np.zeros((1, 49, 3))),
        ValueError,
        "triggers",
    ),
    raises(
        "repeated-trigger",
        lambda c: fix_shape_rig(c.rig, [[1, 1]], lambda w: np.asarray(evaluate_batch(c.rig, w))),
        ValueError,
        "triggers",
    ),
    handled(
        "fix-reproduces-the-sculpt-at-its-corner",
        lambda c: fix_shape_rig(
            c.rig, [[0, 1]], lambda w: np.asarray(evaluate_batch(c.rig, w)) + 0.01
        ),
        lambda rig, c: np.testing.assert_allclose(
            np.asarray(evaluate_batch(rig, np.array([[1, 1, 0, 0.0]]))),
            np.asarray(evaluate_batch(c.rig, np.array([[1, 1, 0, 0.0]]))) + 0.01,
            atol=1e-6,
        ),
    ),
]


@pytest.mark.parametrize("case", FIX_SHAPE_RIG)
def test_fix_shape_rig(case, ctx):
    run_case(case, ctx)


APPLY = [
    raises(
        "nan-pose",
        lambda c: apply(c.model, np.full(4, np.nan), np.asarray(c.rig.neutral)),
        ValueError,
        "weights",
    ),
    raises(
        "pose-width",
        lambda c: apply(c.model, np.zeros(3), np.asarray(c.rig.neutral)),
        ValueError,
        "weights",
    ),
    raises(
        "nan-posed-mesh",
        lambda c: apply(c.model, np.zeros(4), np.full((49, 3), np.nan)),
        ValueError,
        "posed",
    ),
    raises("gui-value-1", lambda c: sigma_from_gui(1.0), ValueError, "sigma_g"),
    raises(
        "layer-eta",
        lambda c: fit_layered(c.rig, c.poses, c.edits, sigma=0.4, eta=-1.0),
        ValueError,
        "eta",
    ),
]


@pytest.mark.parametrize("case", APPLY)
def test_apply_and_layers(case, ctx):
    run_case(case, ctx)


@pytest.fixture(scope="module")
def width_ctx(ctx):
    """ctx plus the prepared edits (world axes) that the width rule reads."""
    data = prepare_edits(ctx.rig, ctx.poses, ctx.edits, local_frames=False)
    two = prepare_edits(ctx.rig, ctx.poses[:2], ctx.edits[:2], local_frames=False)
    return types.SimpleNamespace(**vars(ctx), data=data, two=two)


FEW_EDITS = [
    raises("two-edits", lambda c: fit_width(c.two), ValueError, "data"),
    raises(
        "negative-se-factor", lambda c: fit_width(c.data, se_factor=-1.0), ValueError, "se_factor"
    ),
    raises("nan-se-factor", lambda c: fit_width(c.data, se_factor=np.nan), ValueError, "se_factor"),
    raises("zero-width-grid", lambda c: fit_width(c.data, grid=[0.0, 0.3]), ValueError, "grid"),
    raises("no-vertices", lambda c: fit_width(c.data, max_vertices=0), ValueError, "max_vertices"),
    raises("short-take", lambda c: temporal_change(np.zeros((2, 5, 3))), ValueError, "frames"),
    raises("nan-take", lambda c: temporal_change(np.full((4, 5, 3), np.nan)), ValueError, "frames"),
    raises(
        "reuse-query-width",
        lambda c: reuse_edits(c.rig, c.poses, c.edits, c.poses[:, :2], [0], tau=1.0, sigma=0.4),
        ValueError,
        "query_poses",
    ),
    raises(
        "reuse-nan-query",
        lambda c: reuse_edits(
            c.rig, c.poses, c.edits, np.full_like(c.poses, np.nan), [0], tau=1.0, sigma=0.4
        ),
        ValueError,
        "query_poses",
    ),
    raises(
        "reuse-roi-range",
        lambda c: reuse_edits(c.rig, c.poses, c.edits, c.poses, [49], tau=1.0, sigma=0.4),
        ValueError,
        "roi",
    ),
    raises(
        "reuse-tau",
        lambda c: reuse_edits(c.rig, c.poses, c.edits, c.poses, [0], tau=0.0, sigma=0.4),
        ValueError,
        "tau",
    ),
    raises(
        "reuse-sigma",
        lambda c: reuse_edits(c.rig, c.poses, c.edits, c.poses, [0], tau=1.0, sigma=-1.0),
        ValueError,
        "sigma",
    ),
    raises(
        "reuse-library-shape",
        lambda c: reuse_edits(c.rig, c.poses, c.edits[:, :-1], c.poses, [0], tau=1.0, sigma=0.4),
        ValueError,
        "edits",
    ),
    handled(
        "one-se-width-at-most-the-loo-minimum",
        lambda c: fit_width(c.data),
        lambda fit, c: np.testing.assert_array_less(fit.sigma, fit.loo_min_sigma * (1 + 1e-9)),
    ),
]


@pytest.mark.parametrize("case", FEW_EDITS)
def test_few_edits(case, width_ctx):
    run_case(case, width_ctx)
