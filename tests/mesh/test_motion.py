"""Mesh quality under motion against closed forms: flips, edge stretch, crossings, rigid fit."""

import numpy as np
import pytest

import canrig_jax.mesh._motion as motion
from canrig_jax.mesh import edge_stretch, flipped_triangles, rigid_residual, self_intersections


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_flipped_triangles_counts_a_mirrored_triangle_only():
    neutral = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0], [2, 1, 0.0]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    moved = neutral.copy()
    moved[2, 1] = -1.0  # the first triangle folds through its edge (0, 1)
    frames = np.stack([neutral, moved, neutral @ _rotation(0).T])
    flips = flipped_triangles(frames, neutral, faces)
    np.testing.assert_array_equal(flips, [[False, False], [True, False], [False, False]])
    # a mask leaves the first triangle out
    assert not flipped_triangles(frames, neutral, faces, mask=np.array([False, True])).any()


def test_edge_stretch_of_a_uniform_scale_is_the_scale():
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=(4, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    frames = np.stack([neutral * 2.5, neutral @ _rotation(2).T + 1.0])
    stretch = edge_stretch(frames, neutral, faces)
    assert stretch.shape == (2, 5)  # five unique edges
    np.testing.assert_allclose(stretch[0], 2.5, rtol=1e-12)
    np.testing.assert_allclose(stretch[1], 1.0, rtol=1e-12)


def test_self_intersections_count_only_crossings_the_motion_made():
    # a triangle in z = 0 and a separate triangle above it, standing up; in frame 1 the second
    # one drops so that two of its edges pierce the first
    flat = [[-1, -1, 0], [2, -1, 0], [-1, 2, 0.0]]
    standing = [[0, 0, 0.5], [0.4, 0, 0.5], [0.2, 0.2, 1.5]]
    neutral = np.array(flat + standing)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    dropped = neutral.copy()
    dropped[3:, 2] -= 1.0
    counts = self_intersections(np.stack([neutral, dropped]), neutral, faces, near=10.0)
    np.testing.assert_array_equal(counts, [0, 2])
    # a crossing already in the neutral is not new
    np.testing.assert_array_equal(self_intersections(dropped[None], dropped, faces, near=10.0), [0])


def _crossings_by_solving(frame, edges, faces):
    """(E, F) bool: edge e passes strictly through triangle f (shares no vertex), by solving
    p + s (q - p) = a + u (b - a) + v (c - a) for (s, u, v) pair by pair."""
    out = np.zeros((len(edges), len(faces)), bool)
    for i, (p, q) in enumerate(edges):
        for j, (a, b, c) in enumerate(faces):
            if {p, q} & {a, b, c}:
                continue
            m = np.stack([frame[q] - frame[p], frame[a] - frame[b], frame[a] - frame[c]], 1)
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            s, u, v = np.linalg.solve(m, frame[a] - frame[p])
            out[i, j] = 0 < s < 1 and u > 0 and v > 0 and u + v < 1
    return out


def test_self_intersections_of_a_crumpled_sheet_are_every_new_crossing():
    # a 6 x 6 grid sheet crumpled by random bumps about a cell wide: the pairs the broad
    # phase and the motion filter leave out must be pairs that never cross
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2)
    neutral = np.c_[g, np.zeros(len(g))]
    i = np.arange(5)[:, None] * 6 + np.arange(5)[None]
    quads = i.ravel()
    faces = np.concatenate(
        [np.c_[quads, quads + 6, quads + 1], np.c_[quads + 1, quads + 6, quads + 7]]
    )
    rng = np.random.default_rng(5)
    frames = []
    for _ in range(6):
        centres, heights = rng.uniform(0, 5, (4, 2)), rng.normal(scale=1.2, size=(4, 3))
        bump = np.exp(-((g[:, None] - centres[None]) ** 2).sum(-1) / 0.6)  # (V, 4)
        frames.append(neutral + bump @ heights)
    frames = np.stack(frames)
    edges = np.unique(
        np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0
    )
    want = [_crossings_by_solving(x, edges, faces).sum() for x in frames]
    assert sum(want) > 0  # the crumpling makes crossings
    counts = self_intersections(frames, neutral, faces, near=100.0)
    np.testing.assert_array_equal(counts, want)


def test_rigid_residual_is_zero_for_a_rigid_motion_and_known_for_a_scale():
    rng = np.random.default_rng(3)
    rest = rng.normal(size=(40, 3))
    moved = np.stack([rest @ _rotation(4).T + 2.0, rest * 1.2])
    residual = rigid_residual(rest, moved)
    assert residual[0] < 1e-12
    centred = rest - rest.mean(axis=0)
    expected = 0.2 * np.sqrt((centred**2).sum(axis=1).mean())  # scale 1.2: best rotation = I
    np.testing.assert_allclose(residual[1], expected, rtol=1e-9)


@pytest.mark.bad_input
def test_bad_frames_are_named():
    neutral = np.zeros((3, 3))
    with pytest.raises(ValueError, match="frames"):
        flipped_triangles(np.zeros((2, 4, 3)), neutral, np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="frames"):
        edge_stretch(np.full((1, 3, 3), np.nan), neutral, np.array([[0, 1, 2]]))


def _crossings_of_every_near_pair(frames, neutral, faces):
    """(T,) per frame, the near pairs of the neutral's broad phase (every one, nothing left
    out for not moving) that the NumPy segment-triangle test finds crossing, in float32."""
    pairs = motion._build_near_pairs(neutral, faces, 0.5)
    seg, tri = pairs.edges[pairs.e], pairs.faces[pairs.f]
    x = np.asarray(frames, np.float32)
    return np.array([motion._segment_crosses_triangle(f[seg], f[tri]).sum() for f in x])


def test_self_intersections_of_a_real_head_in_motion_are_every_near_pair_that_crosses(data_dir):
    # the MakeHuman head under its own shapes at 1.5 and random sparse combinations (lips
    # and lids through each other): the motion filter and the compiled, frame-batched test
    # against the NumPy test of every near pair of the broad phase in every frame
    from canrig_jax.autorig import load_makehuman
    from canrig_jax.rig import random_sparse_poses

    head = load_makehuman(data_dir)
    neutral = np.asarray(head.neutral, np.float64)
    deltas = np.asarray(head.deltas, np.float64)
    weights = 1.5 * random_sparse_poses(np.random.default_rng(0), 11, list(head.names))
    frames = neutral + np.einsum("tk,kvc->tvc", weights, deltas)
    motion._NEAR_PAIRS.clear()
    counts = self_intersections(frames, neutral, head.faces)
    want = _crossings_of_every_near_pair(frames, neutral, np.asarray(head.faces, np.int64))
    assert want.sum() > 0
    np.testing.assert_array_equal(counts, want)


def test_self_intersections_reuse_a_neutral_s_broad_phase_only_for_that_neutral():
    # one neutral's near pairs are built once; another neutral with the same triangles (the
    # sheet bent) gets its own, and each gives what a fresh start gives
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2)
    flat = np.c_[g, np.zeros(len(g))]
    bent = np.c_[g, 0.3 * (g[:, 0] - 2.5) ** 2]
    quads = (np.arange(5)[:, None] * 6 + np.arange(5)[None]).ravel()
    faces = np.concatenate(
        [np.c_[quads, quads + 6, quads + 1], np.c_[quads + 1, quads + 6, quads + 7]]
    )
    rng = np.random.default_rng(2)
    frames = {
        n: x + rng.normal(scale=0.8, size=(5, *x.shape))
        for n, x in (("flat", flat), ("bent", bent))
    }
    fresh = {}
    for name, neutral in (("flat", flat), ("bent", bent)):
        motion._NEAR_PAIRS.clear()
        fresh[name] = self_intersections(frames[name], neutral, faces, near=3.0)
    motion._NEAR_PAIRS.clear()
    for name, neutral in (("flat", flat), ("bent", bent), ("flat", flat)):
        np.testing.assert_array_equal(
            self_intersections(frames[name], neutral, faces, near=3.0), fresh[name]
        )
    assert len(motion._NEAR_PAIRS) == 2
    assert sum(fresh["flat"]) > 0


@pytest.mark.parametrize("seed", range(4))
def test_compiled_crossing_test_is_the_numpy_test(seed):
    # random segments and triangles sharing no vertex (what self_intersections passes; the
    # padding shares one and is not valid): the compiled count per frame is the NumPy test's
    # in float32. (Cases within rounding of the test's thresholds, a segment ending on the
    # triangle's plane, may go either way: the compiled program rounds in its own order.)
    rng = np.random.default_rng(seed)
    n_vertices, n_pairs = 60, 4000
    x = rng.normal(size=(10, n_vertices, 3)).astype(np.float32)
    seg = rng.integers(0, n_vertices, (n_pairs, 2)).astype(np.int32)
    tri = rng.integers(0, n_vertices, (n_pairs, 3)).astype(np.int32)
    valid = (rng.random(n_pairs) < 0.9) & ~(seg[:, :, None] == tri[:, None, :]).any(axis=(1, 2))
    counts = np.asarray(motion._count_crossings(x, seg, tri, valid))
    want = [(motion._segment_crosses_triangle(f[seg], f[tri]) & valid).sum() for f in x]
    assert sum(want) > 0
    np.testing.assert_array_equal(counts, want)
