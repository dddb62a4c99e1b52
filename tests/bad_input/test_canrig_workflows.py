"""Bad inputs of the neural rig (``NeuralRig``: handles, edits, layouts) and its workflows
(pose A to B, layers, clip editing, dialogue replacement): each raises naming the argument
before any JIT compilation, or is handled without NaN."""

from __future__ import annotations

import dataclasses
import types

import jax
import numpy as np
import optimistix as optx
import pytest

from canrig_jax.canrig import (
    FitOptions,
    NeuralRig,
    ShapePreservingCANRig,
    clip_edit,
    dialogue_replacement,
    expression_region,
    interior_vertices,
    iterative_layers,
    pose_a_to_b,
)

from .conftest import handled, raises, run_case


@pytest.fixture(scope="module")
def ctx(ict_face):
    neutral = np.asarray(ict_face.neutral, np.float32)
    rig = NeuralRig(
        ShapePreservingCANRig(neutral, key=jax.random.PRNGKey(0)), neutral, ict_face.faces
    )
    handles = rig.handles(np.array([10, 2000, 5000, 8000]))
    rng = np.random.default_rng(0)
    pose = neutral + rng.normal(0, 0.05, neutral.shape).astype(np.float32)
    clip = np.stack([neutral, pose, neutral, pose, neutral])
    nan_pose = pose.copy()
    nan_pose[3, 1] = np.nan
    return types.SimpleNamespace(
        rig=rig,
        ict_face=ict_face,
        handles=handles,
        d=np.zeros((4, 3), np.float32),
        neutral=neutral,
        pose=pose,
        nan_pose=nan_pose,
        clip=clip,
        nowhere=np.zeros(rig.n_vertices, bool),
    )


NEURAL_RIG = [
    raises(
        "model-not-a-canrig",
        lambda c: NeuralRig("model", c.neutral, c.ict_face.faces),
        TypeError,
        "model",
    ),
    raises("duplicated-handles", lambda c: c.rig.handles(np.array([5, 9, 5])), ValueError, "index"),
    raises("float-handles", lambda c: c.rig.handles(np.array([5.0, 9.0])), ValueError, "index"),
    raises(
        "base-wrong-shape",
        lambda c: c.rig.edit(c.handles, c.d, 1.0, 3.0, base=c.neutral[:-1]),
        ValueError,
        "base",
    ),
    raises(
        "base-nan",
        lambda c: c.rig.edit(c.handles, c.d, 1.0, 3.0, base=c.nan_pose),
        ValueError,
        "base",
    ),
    raises(
        "base-complex",
        lambda c: c.rig.edit(c.handles, c.d, 1.0, 3.0, base=c.pose + 1j),
        TypeError,
        "base",
    ),
    raises(
        "beta-nan", lambda c: c.rig.edit(c.handles, c.d, 1.0, 3.0, beta=np.nan), ValueError, "beta"
    ),
    raises(
        "displacements-inf",
        lambda c: c.rig.edit(c.handles, c.d + np.inf, 1.0, 3.0),
        ValueError,
        "displacements",
    ),
    raises(
        "layout-negative-radius", lambda c: c.rig.layout(c.handles, -1.0, 3.0), ValueError, "radius"
    ),
    raises(
        "layout-too-narrow",
        lambda c: c.rig.layout(c.handles, 4.0, 3.0, width=0),
        ValueError,
        "width",
    ),
    raises(
        "layout-parts-not-summing-to-1",
        lambda c: c.rig.layout(c.handles, 4.0, 3.0, parts=(0.5, 0.6)),
        ValueError,
        "parts",
    ),
    raises(
        "layout-parts-negative",
        lambda c: c.rig.layout(c.handles, 4.0, 3.0, parts=(1.5, -0.5)),
        ValueError,
        "parts",
    ),
    raises(
        "layout-parts-with-width",
        lambda c: c.rig.layout(c.handles, 4.0, 3.0, width=8, parts=(0.5, 0.5)),
        ValueError,
        "width",
    ),
    raises(
        "layout-multiple-zero",
        lambda c: c.rig.layout(c.handles, 4.0, 3.0, multiple=0),
        ValueError,
        "multiple",
    ),
    raises(
        "handles-of-another-rig",
        lambda c: c.rig.edit(dataclasses.replace(c.handles, block_distance=c.d), c.d, 1.0, 3.0),
        ValueError,
        "handles",
    ),
    handled(
        "integer-base-is-converted",
        lambda c: c.rig(c.handles, c.d, 1.0, 3.0, base=np.round(c.neutral).astype(np.int64)),
        lambda out, c: np.testing.assert_array_equal(out, np.round(c.neutral)),
    ),
]


@pytest.mark.parametrize("case", NEURAL_RIG)
def test_neural_rig(case, ctx):
    run_case(case, ctx)


POSE_A_TO_B = [
    raises(
        "target-nan",
        lambda c: pose_a_to_b(c.rig, c.handles, c.neutral, c.nan_pose, 1.0, 3.0),
        ValueError,
        "target",
    ),
    raises(
        "source-wrong-shape",
        lambda c: pose_a_to_b(c.rig, c.handles, c.neutral[None], c.pose, 1.0, 3.0),
        ValueError,
        "source",
    ),
    raises(
        "region-selects-nothing",
        lambda c: pose_a_to_b(
            c.rig, c.handles, c.neutral, c.pose, 1.0, 3.0, fit=True, region=c.nowhere
        ),
        ValueError,
        "region",
    ),
    raises(
        "region-wrong-shape",
        lambda c: pose_a_to_b(c.rig, c.handles, c.neutral, c.pose, 1.0, 3.0, region=np.ones(7)),
        ValueError,
        "region",
    ),
    raises(
        "region-negative",
        lambda c: pose_a_to_b(
            c.rig, c.handles, c.neutral, c.pose, 1.0, 3.0, region=-np.ones(c.rig.n_vertices)
        ),
        ValueError,
        "region",
    ),
    raises("fit-no-steps", lambda c: FitOptions(max_steps=0), ValueError, "max_steps"),
    raises("fit-negative-penalty", lambda c: FitOptions(penalty=-1.0), ValueError, "penalty"),
    handled(
        "one-step-fit-reports-its-result-without-nan",
        lambda c: pose_a_to_b(
            c.rig,
            c.handles,
            c.neutral,
            c.pose,
            1.0,
            3.0,
            fit=True,
            options=FitOptions(max_steps=1),
        ),
        lambda s, c: (
            np.testing.assert_array_equal(s.result == optx.RESULTS.successful, False),
            np.testing.assert_array_less(float(s.error), float(s.direct_error) + 1e-12),
        ),
    ),
]


@pytest.mark.parametrize("case", POSE_A_TO_B)
def test_pose_a_to_b(case, ctx):
    run_case(case, ctx)


WORKFLOWS = [
    raises(
        "layers-empty-schedule",
        lambda c: iterative_layers(c.rig, c.neutral, c.pose, [], 3.0),
        ValueError,
        "schedule",
    ),
    raises(
        "layers-schedule-without-handles",
        lambda c: iterative_layers(c.rig, c.neutral, c.pose, [([1, 2], 1.0)], 3.0),
        ValueError,
        "schedule[0]",
    ),
    raises(
        "clip-wrong-shape",
        lambda c: clip_edit(c.rig, c.clip[:, :-1], 2, c.handles, c.d, 1.0, 3.0, 1),
        ValueError,
        "clip",
    ),
    raises(
        "clip-complex",
        lambda c: clip_edit(c.rig, c.clip + 1j, 2, c.handles, c.d, 1.0, 3.0, 1),
        TypeError,
        "clip",
    ),
    raises(
        "clip-nan",
        lambda c: clip_edit(c.rig, np.stack([c.nan_pose] * 5), 2, c.handles, c.d, 1.0, 3.0, 1),
        ValueError,
        "clip",
    ),
    raises(
        "clip-frame-outside",
        lambda c: clip_edit(c.rig, c.clip, 5, c.handles, c.d, 1.0, 3.0, 1),
        ValueError,
        "frame",
    ),
    raises(
        "clip-fade-window-outside",
        lambda c: clip_edit(c.rig, c.clip, 1, c.handles, c.d, 1.0, 3.0, 2),
        ValueError,
        "half_window",
    ),
    raises(
        "clip-negative-window",
        lambda c: clip_edit(c.rig, c.clip, 1, c.handles, c.d, 1.0, 3.0, -1),
        ValueError,
        "half_window",
    ),
    raises(
        "dialogue-frame-mismatch",
        lambda c: dialogue_replacement(c.rig, c.clip, c.clip[:3], c.handles, 1.0, 3.0),
        ValueError,
        "target",
    ),
    raises(
        "dialogue-target-nan",
        lambda c: dialogue_replacement(
            c.rig, c.clip, np.stack([c.nan_pose] * 5), c.handles, 1.0, 3.0
        ),
        ValueError,
        "target",
    ),
    raises(
        "dialogue-mouth-mask-empty",
        lambda c: dialogue_replacement(
            c.rig, c.clip, c.clip, c.handles, 1.0, 3.0, region=c.nowhere
        ),
        ValueError,
        "region",
    ),
    raises(
        "region-prefix-matches-nothing",
        lambda c: expression_region(c.ict_face, include=("tongue",)),
        ValueError,
        "include",
    ),
    raises(
        "interior-of-nothing",
        lambda c: interior_vertices(c.rig, c.nowhere, 1.0),
        ValueError,
        "region",
    ),
    handled(
        "zero-window-edits-one-frame",
        lambda c: clip_edit(c.rig, c.clip, 2, c.handles, c.d + 0.1, 1.0, 3.0, 0),
        lambda out, c: (
            np.testing.assert_array_equal(out.clip[[0, 1, 3, 4]], c.clip[[0, 1, 3, 4]]),
            np.testing.assert_array_equal(out.fade, [0, 0, 1, 0, 0]),
        ),
    ),
]


@pytest.mark.parametrize("case", WORKFLOWS)
def test_workflows(case, ctx):
    run_case(case, ctx)
