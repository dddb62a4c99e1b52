"""PSE / WPSE fitting and evaluation against independent NumPy computations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import canrig_jax.wpse._frames as frames_module  # patched: the grouping cost
from canrig_jax.papers.wpse import (
    NumpyEditEvaluator,
    reference_frames,
    reference_vertex_frames,
    time_runtime,
)
from canrig_jax.rig import BlendshapeRig, evaluate, evaluate_batch
from canrig_jax.wpse import apply, blendshape_metric, fit_pose_space_edit
from canrig_jax.wpse._frames import frame_matrices, local_frames, local_to_world
from canrig_jax.wpse._pse import correction, edited_mesh

# compiled once per frame layout (op by op, every ring group's operations compile on their own)
jit_frame_matrices = jax.jit(frame_matrices)
jit_local_to_world = jax.jit(local_to_world)


def loop_wpse(rig, poses, edits, sigma, weights, metric="weighted", epsilon=1e-3):
    """World-frame (W)PSE at ``weights`` by a per-vertex loop of float64 solves."""
    v = rig.n_vertices
    if metric == "weighted":
        alpha = blendshape_metric(np.asarray(rig.deltas), epsilon).astype(np.float64)
    else:
        alpha = np.ones((v, rig.n_blendshapes))
    out = np.zeros((v, 3))
    for vertex in range(v):
        a = alpha[vertex]
        phi = np.array(
            [[np.exp(-np.sum(a * (p - q) ** 2) / (2 * sigma**2)) for q in poses] for p in poses]
        )
        x = np.linalg.solve(phi, edits[:, vertex].astype(np.float64))
        k = np.array([np.exp(-np.sum(a * (weights - p) ** 2) / (2 * sigma**2)) for p in poses])
        out[vertex] = k @ x
    return out


@pytest.mark.parametrize("metric", ["weighted", "euclidean"])
def test_world_frame_matches_per_vertex_loop(tiny_rig, tiny_edits, metric):
    poses, edits = tiny_edits
    sigma = 0.3 if metric == "weighted" else 0.8
    model = fit_pose_space_edit(
        tiny_rig, poses, edits, sigma=sigma, metric=metric, local_frames=False, ridge=0.0
    )
    w = np.random.default_rng(3).uniform(0, 1, tiny_rig.n_blendshapes).astype(np.float32)
    posed = evaluate(tiny_rig, w)
    got = np.asarray(apply(model, w, posed)) - np.asarray(posed)
    expected = loop_wpse(tiny_rig, poses, edits, sigma, w, metric)
    np.testing.assert_allclose(got, expected, atol=2e-4 * np.abs(edits).max())


@pytest.mark.parametrize("frames", [False, True])
@pytest.mark.parametrize("metric", ["weighted", "euclidean"])
def test_edits_reproduced_at_their_poses(tiny_rig, tiny_edits, metric, frames):
    poses, edits = tiny_edits
    model = fit_pose_space_edit(
        tiny_rig, poses, edits, sigma=0.4, metric=metric, local_frames=frames
    )
    posed = evaluate_batch(tiny_rig, poses)
    got = jax.vmap(apply, (None, 0, 0))(model, poses, posed) - posed
    np.testing.assert_allclose(got, edits, atol=1e-3 * np.abs(edits).max())


def test_single_edit_closed_form(tiny_rig):
    """One edit: d(w) = d_1 exp(-||w - w_1||^2 / (2 sigma^2)) (Euclidean PSE)."""
    pose = np.array([[0.5, 0.2, 0.0, 0.9]], np.float32)
    edit = np.full((1, tiny_rig.n_vertices, 3), 0.01, np.float32)
    model = fit_pose_space_edit(
        tiny_rig, pose, edit, sigma=0.5, metric="euclidean", local_frames=False, ridge=0.0
    )
    w = np.array([0.1, 0.2, 0.3, 0.4], np.float32)
    factor = np.exp(-np.sum((w - pose[0]) ** 2) / (2 * 0.25))
    np.testing.assert_allclose(correction(model, w), edit[0] * factor, rtol=1e-5)


def test_local_frames_match_reference(tiny_rig):
    vertices = np.array([0, 5, 24, 48])
    frames = local_frames(tiny_rig.faces, vertices, tiny_rig.n_vertices)
    posed = evaluate(tiny_rig, jnp.array([0.3, 0.9, 0.1, 0.5]))
    got = np.asarray(jit_frame_matrices(frames, posed))
    expected = reference_frames(posed, tiny_rig.faces, vertices, np.asarray(frames.neighbour))
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(
        got @ np.swapaxes(got, 1, 2), np.broadcast_to(np.eye(3), got.shape), atol=1e-5
    )
    np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=1e-5)


@pytest.mark.parametrize("group_cost", [0, 4096, 10**9])
def test_local_frames_all_degrees_match_numpy(tiny_rig, monkeypatch, group_cost):
    """Every vertex of the grid (degrees 1 to 6) against the plain NumPy accumulation, in
    order and in scrambled-degree order, with one ring group per degree (cost 0), the
    default grouping, and all degrees in one padded group."""
    monkeypatch.setattr(frames_module, "GROUP_COST", group_cost)
    posed = np.asarray(evaluate(tiny_rig, jnp.array([0.8, 0.1, 0.6, 0.3])))
    for vertices in (np.arange(tiny_rig.n_vertices), np.array([48, 0, 6, 7, 24, 42, 13])):
        frames = local_frames(tiny_rig.faces, vertices, tiny_rig.n_vertices)
        degree = np.bincount(np.asarray(tiny_rig.faces).reshape(-1))[vertices]
        if group_cost == 0:
            assert sorted(r.shape[1] for r in frames.rings) == sorted(set(degree.tolist()))
        if group_cost == 10**9:
            assert [r.shape[1] for r in frames.rings] == [degree.max()]
        got = np.asarray(jit_frame_matrices(frames, posed))
        expected = reference_vertex_frames(
            posed, tiny_rig.faces, vertices, np.asarray(frames.neighbour)
        )
        np.testing.assert_allclose(got, expected, atol=1e-6)
        offsets = np.random.default_rng(0).normal(size=(len(vertices), 3)).astype(np.float32)
        np.testing.assert_allclose(
            jit_local_to_world(frames, posed, offsets),
            np.einsum("sij,sj->si", expected, offsets),
            atol=1e-6,
        )


@pytest.mark.parametrize("group_cost", [0, 10**9])
def test_local_frames_rings_hold_each_vertex_incident_triangles(tiny_rig, monkeypatch, group_cost):
    monkeypatch.setattr(frames_module, "GROUP_COST", group_cost)
    vertices = np.array([3, 0, 48, 24, 6])
    frames = local_frames(tiny_rig.faces, vertices, tiny_rig.n_vertices)
    stacked = [row for ring in frames.rings for row in np.asarray(ring).tolist()]
    order = np.asarray(frames.ring_order)
    assert sorted(order.tolist()) == list(range(len(vertices)))
    used = np.asarray(frames.faces)
    for s, v in enumerate(vertices):
        row = stacked[order[s]]
        ring = [f for f in row if f < len(used)]
        assert all(f == len(used) for f in row[len(ring) :])  # padding: the zero normal
        assert len(ring) == len(set(ring)) == int(np.sum(np.asarray(frames.weight)[s]))
        assert all(v in used[f] for f in ring)
        assert set(ring) == set(np.asarray(frames.incident)[s].tolist())


def test_local_frames_of_no_vertices(tiny_rig):
    frames = local_frames(tiny_rig.faces, np.zeros(0, np.int64), tiny_rig.n_vertices)
    posed = evaluate(tiny_rig, jnp.zeros(4))
    assert frame_matrices(frames, posed).shape == (0, 3, 3)
    assert local_to_world(frames, posed, jnp.zeros((0, 3))).shape == (0, 3)


def test_local_frame_edit_turns_with_the_mesh(tiny_rig, tiny_edits):
    """Rotating the whole rig (neutral and shapes) and the sculpted edits by R rotates the
    correction by R, at every pose: the edit lives in the posed mesh's frames."""
    poses, edits = tiny_edits
    angle = 0.7
    r = np.array(
        [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]],
        np.float32,
    )
    turned = BlendshapeRig(
        np.asarray(tiny_rig.neutral) @ r.T,
        np.asarray(tiny_rig.deltas) @ r.T,
        (),
        tiny_rig.names,
        tiny_rig.faces,
    )
    model = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    turned_model = fit_pose_space_edit(turned, poses, edits @ r.T, sigma=0.4)
    w = jnp.array([0.2, 0.7, 0.4, 0.1])
    np.testing.assert_allclose(
        correction(turned_model, w, evaluate(turned, w)),
        np.asarray(correction(model, w, evaluate(tiny_rig, w))) @ r.T,
        atol=1e-5,
    )
    # the stored coefficients themselves are the same: the edit is pose-relative
    np.testing.assert_allclose(turned_model.coefficients, model.coefficients, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_support_restriction_and_numpy_evaluator(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    edits = edits.copy()
    edits[:, :10] = 0.0  # vertices no edit moves
    model = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    assert model.vertices.shape[0] == tiny_rig.n_vertices - 10
    w = np.array([0.3, 0.3, 0.3, 0.3], np.float32)
    posed = np.asarray(evaluate(tiny_rig, w))
    got = np.asarray(apply(model, w, posed))
    np.testing.assert_array_equal(got[:10], posed[:10])
    np.testing.assert_allclose(got, NumpyEditEvaluator(model)(w, posed), atol=1e-5)


def test_time_runtime_passes_and_agreement(tiny_rig, tiny_edits):
    """One timing per frame and pass for JAX and NumPy; both compute the same mesh."""
    poses, edits = tiny_edits
    model = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    weights = np.random.default_rng(3).uniform(0, 1, (4, tiny_rig.n_blendshapes))
    posed = np.asarray(evaluate_batch(tiny_rig, weights.astype(np.float32)))
    timed = time_runtime(model, weights.astype(np.float32), posed, passes=3)
    assert timed["jax_seconds"].shape == timed["numpy_seconds"].shape == (12,)
    assert timed["max_abs_diff"] < 1e-5
    with pytest.raises(ValueError, match="passes"):
        time_runtime(model, weights, posed, passes=0)


def test_jit_vmap_and_edited_mesh(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    model = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    ws = np.random.default_rng(0).uniform(0, 1, (6, tiny_rig.n_blendshapes)).astype(np.float32)
    batched = jax.jit(jax.vmap(lambda w: edited_mesh(model, tiny_rig, w)))(ws)
    for w, mesh in zip(ws, batched, strict=True):
        np.testing.assert_allclose(mesh, edited_mesh(model, tiny_rig, w), atol=1e-5)


# --- duplicated poses and bad input ----------------------------------------------------------


def test_duplicated_poses_raise_or_merge(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    poses = np.concatenate([poses, poses[:1]])
    edits = np.concatenate([edits, 3 * edits[:1]])
    with pytest.raises(ValueError, match="same pose"):
        fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    model = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4, duplicates="merge")
    assert model.n_edits == len(poses) - 1
    posed = evaluate(tiny_rig, poses[0])
    np.testing.assert_allclose(
        apply(model, poses[0], posed) - posed, 2 * edits[0], atol=1e-3 * np.abs(edits).max()
    )


@pytest.mark.bad_input
def test_bad_input(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    fit = fit_pose_space_edit
    with pytest.raises(ValueError, match="edits"):
        fit(tiny_rig, poses, edits[:, :-1], sigma=0.4)
    with pytest.raises(ValueError, match="poses"):
        fit(tiny_rig, poses[:, :-1], edits, sigma=0.4)
    with pytest.raises(ValueError, match="edits"):
        fit(tiny_rig, poses[:-1], edits, sigma=0.4)
    for sigma in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="sigma"):
            fit(tiny_rig, poses, edits, sigma=sigma)
    bad = edits.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="edits"):
        fit(tiny_rig, poses, bad, sigma=0.4)
    with pytest.raises(ValueError, match="metric"):
        fit(tiny_rig, poses, edits, sigma=0.4, metric="cosine")
    with pytest.raises(ValueError, match="ridge"):
        fit(tiny_rig, poses, edits, sigma=0.4, ridge=-1.0)
    model = fit(tiny_rig, poses, edits, sigma=0.4)
    posed = evaluate(tiny_rig, poses[0])
    with pytest.raises(ValueError, match="weights"):
        apply(model, poses[0][:-1], posed)
    with pytest.raises(ValueError, match="posed"):
        apply(model, poses[0], posed[:-1])
    with pytest.raises(ValueError, match="posed"):
        apply(model, poses[0], jnp.full_like(posed, jnp.nan))


def test_rest_pose_anchor_zeroes_the_correction_at_rest(tiny_rig, tiny_edits):
    poses, edits = tiny_edits
    rest = np.zeros(tiny_rig.n_blendshapes, np.float32)
    plain = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4)
    anchored = fit_pose_space_edit(tiny_rig, poses, edits, sigma=0.4, rest_pose=True)
    assert anchored.n_edits == plain.n_edits + 1
    posed = evaluate(tiny_rig, rest)
    assert np.abs(np.asarray(correction(plain, rest, posed))).max() > 1e-3
    np.testing.assert_allclose(
        correction(anchored, rest, posed), 0.0, atol=1e-3 * np.abs(edits).max()
    )
    at_edits = jax.vmap(apply, (None, 0, 0))(anchored, poses, evaluate_batch(tiny_rig, poses))
    np.testing.assert_allclose(
        at_edits - evaluate_batch(tiny_rig, poses),
        edits,
        atol=1e-3 * np.abs(edits).max(),
    )
