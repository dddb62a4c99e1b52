"""CANRig workflows on the ICT face: the one forward pass over batches and layouts, the exact
structured Jacobian, fitted pose A to B (never worse than direct), layers (non-increasing
exactly), clip editing and dialogue replacement (exact zeros outside the edit)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import (
    CLAMP,
    CANRig,
    FitOptions,
    NeuralRig,
    ShapePreservingCANRig,
    clip_edit,
    dialogue_replacement,
    expression_region,
    influence_mask,
    influence_reach,
    interior_vertices,
    iterative_layers,
    pose_a_to_b,
)
from canrig_jax.canrig._attention_fit import apply_jacobian, displacement_jacobian, normal_matrix
from canrig_jax.canrig._layout import DENSE, PartsLayout
from canrig_jax.canrig._rig import deform
from canrig_jax.canrig._workflows import smoothstep_fade
from canrig_jax.mesh import farthest_point_vertices
from canrig_jax.rig import evaluate_batch

FALLOFF = 3.0


def _rig(ict_face, variant):
    neutral = np.asarray(ict_face.neutral, np.float32)
    options = {"fourier": 2, "interpolation_prior": True}
    if variant == "shape_preserving":
        model = ShapePreservingCANRig(
            neutral,
            key=jax.random.PRNGKey(1),
            query_modulation=True,
            value_position=True,
            **options,
        )
    else:
        model = CANRig(neutral, key=jax.random.PRNGKey(1), **options)
    return NeuralRig(model, neutral, np.asarray(ict_face.faces))


@pytest.fixture(scope="module")
def rig(ict_face):
    """The shape-preserving model with every option (random weights: the properties tested
    here hold for any weights)."""
    return _rig(ict_face, "shape_preserving")


@pytest.fixture(scope="module")
def poses(ict_face, sparse_poses):
    """Real ICT expressions (sparse poses of the rig), (4, V, 3)."""
    return np.asarray(evaluate_batch(ict_face, sparse_poses[:4]))


@pytest.fixture(scope="module")
def few_handles(rig):
    index = farthest_point_vertices(np.asarray(rig.canonical), 10, graph=rig.graph)
    return rig.handles(index)


@pytest.mark.parametrize(
    "variant",
    # most of the cost is compiling the dense pass and jax.jacfwd: the second model's check
    # runs in -m slow
    # (the default run checks the blocks through J^T W J: test_normal_matrix_equals_autodiff)
    [pytest.param(v, marks=pytest.mark.slow) for v in ("shape_preserving", "canrig")],
)
def test_jacobian_equals_autodiff(variant, ict_face, poses):
    """The structured 3 x 3 blocks equal jax.jacfwd of the forward pass, dense and blocked."""
    rig = _rig(ict_face, variant)
    few_handles = rig.handles(farthest_point_vertices(np.asarray(rig.canonical), 4))
    rng = np.random.default_rng(0)
    displacements = rng.normal(0, 0.3, (few_handles.n_handles, 3)).astype(np.float32)
    edit = rig.edit(few_handles, displacements, 5.0, FALLOFF, base=poses[0], beta=0.4)
    for layout in (DENSE, rig.layout(few_handles, 5.0, FALLOFF)):
        shape, blocks = displacement_jacobian(rig.model, rig.queries, rig.canonical, edit, layout)

        def forward(d, layout=layout):
            return deform(rig.model, rig.queries, rig.canonical, edit.with_displacements(d), layout)

        expected = jax.jacfwd(forward)(edit.displacements)  # (V, 3, H, 3)
        basis = jnp.eye(few_handles.n_handles * 3).reshape(-1, few_handles.n_handles, 3)
        columns = jax.vmap(lambda t, b=blocks, lo=layout: apply_jacobian(b, t, lo))(basis)
        ours = jnp.moveaxis(columns, 0, -1).reshape(expected.shape)
        scale = float(jnp.abs(expected).max())
        assert scale > 0.1
        np.testing.assert_allclose(np.asarray(ours), np.asarray(expected), atol=2e-5 * scale)
        np.testing.assert_allclose(shape, forward(edit.displacements), atol=1e-6)


@pytest.mark.slow
def test_normal_matrix_equals_autodiff(rig, poses):
    """J^T W J assembled from the blocks (one-width and parts layouts, with a region weight)
    equals the one from jax.jacfwd of the forward pass."""
    handles = rig.handles(np.random.default_rng(6).choice(rig.n_vertices, 12, replace=False))
    displacements = np.random.default_rng(7).normal(0, 0.3, (12, 3)).astype(np.float32)
    edit = rig.edit(handles, displacements, 3.0, FALLOFF, base=poses[1])
    weight = jnp.asarray(np.random.default_rng(8).uniform(0, 1, rig.n_vertices), jnp.float32)

    def forward(d):
        return deform(rig.model, rig.queries, rig.canonical, edit.with_displacements(d))

    jac = jax.jacfwd(forward)(edit.displacements).reshape(rig.n_vertices, 3, 36)
    expected = np.einsum("vip,v,viq->pq", np.asarray(jac, np.float64), np.asarray(weight), jac)
    scale = np.abs(expected).max()
    assert scale > 0.1
    for layout in (
        rig.layout(handles, 3.0, FALLOFF, multiple=8),
        rig.layout(handles, 3.0, FALLOFF, multiple=8, parts=(0.5, 0.5)),
    ):
        _, blocks = displacement_jacobian(rig.model, rig.queries, rig.canonical, edit, layout)
        ours = np.asarray(normal_matrix(blocks, weight, 12, layout))
        np.testing.assert_allclose(ours, expected, atol=1e-4 * scale)


def test_layout_width_rules(rig):
    """The width is the next power of two (default) or the next multiple above the largest
    count of handles within reach of a block, and both layouts give the dense result."""
    handles = rig.handles(np.random.default_rng(9).choice(rig.n_vertices, 50, replace=False))
    reach = influence_reach(np.full(50, 2.0), np.full(50, FALLOFF), rig.model.clamp)
    most = int((np.asarray(handles.block_distance) <= reach).sum(axis=1).max())
    power = rig.layout(handles, 2.0, FALLOFF)
    tight = rig.layout(handles, 2.0, FALLOFF, multiple=8)
    assert power.width == min(1 << (most - 1).bit_length(), 50)
    assert tight.width == min(-(-most // 8) * 8, 50) and tight.width <= power.width
    edit = rig.edit(handles, np.full((50, 3), 0.2, np.float32), 2.0, FALLOFF)
    dense = np.asarray(rig.deform(edit, DENSE))
    for layout in (power, tight):
        np.testing.assert_allclose(np.asarray(rig.deform(edit, layout)), dense, atol=5e-6)


@pytest.mark.slow
def test_model_steps_take_any_leading_shape(rig, few_handles, poses):
    """encode -> attention -> decode on a (2, 3) batch equals the unbatched steps; deform
    vmapped over edits equals a loop of single calls."""
    model = rig.model
    rng = np.random.default_rng(1)
    handle_base = jnp.asarray(poses[:2][:, few_handles.index])  # (2, H, 3)
    d = jnp.asarray(rng.normal(0, 0.2, (2, 3) + handle_base.shape[1:]), jnp.float32)
    batched = model.encode_values(d, handle_base[:, None])  # (2, 3, heads, H, e)
    single = model.encode_values(d[1, 2], handle_base[1])
    np.testing.assert_allclose(np.asarray(batched[1, 2]), np.asarray(single), atol=1e-6)
    edits = [
        rig.edit(few_handles, rng.normal(0, 0.2, (10, 3)), 2.0, FALLOFF, base=p) for p in poses
    ]
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *edits)
    layout = rig.layout(few_handles, 2.0, FALLOFF)
    vmapped = eqx.filter_vmap(lambda e: deform(model, rig.queries, rig.canonical, e, layout))(
        stacked
    )
    for i, edit in enumerate(edits):
        np.testing.assert_allclose(
            np.asarray(vmapped[i]), np.asarray(rig.deform(edit, DENSE)), atol=5e-6
        )


@pytest.mark.slow  # 15-24 s; never-worse is also checked by the region and layer tests
def test_fit_is_never_worse_and_minimises(rig, poses):
    """Fitted A to B: error <= direct and <= the base (exactly), no NaN, the reported error
    the measured one; and the gradient of the objective (plain autodiff of the forward
    pass, independent of the structured Jacobian) is much smaller than at the start."""
    handles = rig.handles(np.random.default_rng(2).choice(rig.n_vertices, 60, replace=False))
    a, b = poses[0], poses[1]
    direct = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF)
    fitted = pose_a_to_b(rig, handles, a, b, 2.0, FALLOFF, fit=True)
    assert float(fitted.error) < float(direct.error)
    assert float(fitted.error) <= float(fitted.base_error)
    assert np.all(np.isfinite(np.asarray(fitted.displacements)))
    edit = rig.edit(handles, direct.displacements, 2.0, FALLOFF, base=a)

    def objective(d):
        shape = deform(rig.model, rig.queries, rig.canonical, edit.with_displacements(d))
        return 0.5 * jnp.sum((shape - b) ** 2)

    gradient = jax.grad(objective)
    start = float(jnp.linalg.norm(gradient(direct.displacements)))
    end = float(jnp.linalg.norm(gradient(fitted.displacements)))
    assert end < 0.2 * start
    measured = np.linalg.norm(np.asarray(fitted.shape) - b, axis=1).mean()
    assert float(fitted.error) == pytest.approx(measured, rel=1e-5)
    # the exact-Jacobian solve reaches the same neighbourhood
    exact = pose_a_to_b(
        rig,
        handles,
        a,
        b,
        2.0,
        FALLOFF,
        fit=True,
        options=FitOptions(exact_jacobian=True, damped=True, max_steps=4),
    )
    assert float(exact.error) <= float(direct.error)
    assert abs(float(exact.error) - float(fitted.error)) < 0.1 * float(direct.error)


@pytest.mark.slow
def test_fit_in_a_region_only_lowers_the_region_error(rig, poses, ict_face):
    """The reported error is the region's measured one, never above direct, and the shape is
    the forward pass of the returned displacements (taken from the solver's state, not
    recomputed)."""
    handles = rig.handles(np.random.default_rng(3).choice(rig.n_vertices, 40, replace=False))
    region = expression_region(ict_face)
    fitted = pose_a_to_b(rig, handles, poses[2], poses[3], 2.0, FALLOFF, fit=True, region=region)
    err = np.linalg.norm(np.asarray(fitted.shape) - poses[3], axis=1)
    assert float(fitted.error) == pytest.approx(err[region].mean(), rel=1e-5)
    assert float(fitted.error) < float(fitted.direct_error)  # the fitted candidate won
    assert int(fitted.chosen) == 0
    edit = rig.edit(handles, fitted.displacements, 2.0, FALLOFF, base=poses[2])
    np.testing.assert_allclose(np.asarray(fitted.shape), np.asarray(rig.deform(edit)), atol=2e-5)


@pytest.mark.slow
def test_parts_layout_is_exact_and_tight(rig, poses):
    """A ``PartsLayout`` covers every vertex exactly once, each part's width holds the most
    handles reaching its blocks, and the forward pass equals the dense one (its J^T W J is
    checked against autodiff in ``test_normal_matrix_equals_autodiff``)."""
    rng = np.random.default_rng(10)
    handles = rig.handles(rng.choice(rig.n_vertices, 60, replace=False))
    parts = rig.layout(handles, 2.0, FALLOFF, multiple=8, parts=(0.5, 0.3, 0.2))
    one = rig.layout(handles, 2.0, FALLOFF, multiple=8)
    assert isinstance(parts, PartsLayout) and len(parts.parts) == 3
    covered = np.zeros(rig.n_vertices, int)
    reach = influence_reach(np.full(60, 2.0), np.full(60, FALLOFF), rig.model.clamp)
    within = np.asarray(handles.block_distance) <= reach
    for part in parts.parts:
        vertices = np.asarray(part.blocks).ravel()
        covered += np.bincount(vertices[vertices < rig.n_vertices], minlength=rig.n_vertices)
        block_rows = [np.flatnonzero((rig.blocks == row).all(axis=1))[0] for row in part.blocks]
        assert part.width >= within[block_rows].sum(axis=1).max()
        assert part.width % 8 == 0 or part.width == 60
    assert np.all(covered == 1)
    assert list(parts.width) == sorted(parts.width) and parts.width[0] < one.width
    edit = rig.edit(handles, rng.normal(0, 0.3, (60, 3)).astype(np.float32), 2.0, FALLOFF)
    edit = edit.with_base(jnp.asarray(poses[1]))
    dense = np.asarray(rig.deform(edit, DENSE))
    np.testing.assert_allclose(np.asarray(rig.deform(edit, parts)), dense, atol=5e-6)


@pytest.mark.slow  # 31 s (three fits); the experiment checks every pair of its 30
def test_fitted_layers_never_increase_exactly(rig, poses):
    rng = np.random.default_rng(4)
    schedule = [
        (rig.handles(rng.choice(rig.n_vertices, n, replace=False)), radius)
        for n, radius in ((6, 4.0), (20, 2.0), (40, 1.0))
    ]
    options = FitOptions()
    fitted = iterative_layers(rig, poses[0], poses[2], schedule, FALLOFF, fit=True, options=options)
    errors = fitted.errors
    assert np.all(np.diff(errors) <= 0.0)
    start = np.linalg.norm(poses[0] - poses[2], axis=1).mean()
    assert errors[0] <= start
    direct = iterative_layers(rig, poses[0], poses[2], schedule, FALLOFF)
    assert errors[0] <= direct.errors[0] * (1 + 1e-6)  # same base: the fit is never worse


def test_smoothstep_fade():
    fade = smoothstep_fade(41, 20, 10)
    assert fade[20] == 1.0
    assert np.all(fade[:10] == 0) and np.all(fade[31:] == 0) and np.all(fade[10:31] > 0)
    np.testing.assert_allclose(fade[10:20], fade[30:20:-1])  # symmetric
    assert np.all(np.diff(fade[9:21]) > 0)
    # zero slope at the window's ends: the fade starts quadratically, well below the first
    # step of a linear fade (1 / 11)
    assert fade[10] < 0.3 / 11


@pytest.mark.slow
def test_clip_edit_is_local_in_time_and_space(rig, poses):
    clip = np.concatenate([poses, poses[::-1], poses])  # 12 real frames
    handles = rig.handles(farthest_point_vertices(np.asarray(rig.canonical), 6, graph=rig.graph))
    displacements = np.random.default_rng(5).normal(0, 0.3, (6, 3)).astype(np.float32)
    edited = clip_edit(rig, clip, 5, handles, displacements, 1.5, FALLOFF, 3)
    lo, hi = edited.window
    assert (lo, hi) == (2, 8)
    outside = np.r_[0:lo, hi + 1 : len(clip)]
    assert np.array_equal(edited.clip[outside], clip[outside])  # bit-identical
    mask = np.asarray(influence_mask(handles.distance, 1.5, FALLOFF, CLAMP))
    unmasked = mask.max(axis=1) == 0
    assert 1000 < unmasked.sum() < rig.n_vertices
    assert np.array_equal(edited.clip[:, unmasked], clip[:, unmasked])
    # the edited frame: the rig with the full displacements on that frame
    expected = rig(handles, displacements, 1.5, FALLOFF, base=clip[5])
    np.testing.assert_allclose(edited.clip[5], np.asarray(expected), atol=1e-6)
    assert not np.allclose(edited.clip[4], clip[4])


@pytest.mark.slow
def test_dialogue_replacement_keeps_the_rest_of_the_face(rig, poses, ict_face):
    mouth = expression_region(ict_face)
    reach = float(influence_reach(1.0, FALLOFF, rig.model.clamp))
    interior = interior_vertices(rig, mouth, reach)
    assert 0 < len(interior) < mouth.sum()
    index = interior[farthest_point_vertices(np.asarray(rig.canonical)[interior], 12)]
    handles = rig.handles(index)
    source, target = poses[:2], poses[2:]
    out = dialogue_replacement(rig, source, target, handles, 1.0, FALLOFF, region=mouth)
    assert np.array_equal(out[:, ~mouth], source[:, ~mouth])  # exactly 0.0 outside the mask
    # frame by frame equals single calls with that frame as base
    for f in range(2):
        single = rig(handles, target[f, index] - source[f, index], 1.0, FALLOFF, base=source[f])
        np.testing.assert_allclose(out[f], np.asarray(single), atol=1e-6)
    unchanged = dialogue_replacement(rig, source, source, handles, 1.0, FALLOFF)
    assert np.array_equal(unchanged, source)  # rig inversion error 0.0 by construction
    fitted = dialogue_replacement(
        rig, source, target, handles, 1.0, FALLOFF, fit=True, region=mouth
    )
    assert np.array_equal(fitted[:, ~mouth], source[:, ~mouth])
    mouth_error = [np.linalg.norm(x - target, axis=-1)[:, mouth].mean() for x in (out, fitted)]
    assert mouth_error[1] <= mouth_error[0] + 1e-6


def test_mouth_region_on_ict(ict_face):
    """The default region holds the vertices jawOpen moves most and none of those eyeBlink
    moves."""
    mouth = expression_region(ict_face)
    deltas = np.linalg.norm(np.asarray(ict_face.deltas), axis=-1)
    names = list(ict_face.names)
    assert mouth[np.argmax(deltas[names.index("jawOpen")])]
    assert not mouth[deltas[names.index("eyeBlink_L")] > 0.1].any()
    assert 0.1 < mouth.mean() < 0.8
