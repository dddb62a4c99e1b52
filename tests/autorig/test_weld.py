"""Clumps of vertices that move as one (``autorig._weld``), on the Rocketbox male head crop:
a head sculpted by other people than ICT's, with vertices a fraction of a millimetre apart
at its mouth and eye corners."""

from __future__ import annotations

import jaxtyping
import numpy as np
import pytest

from canrig_jax.autorig import load_rocketbox_head
from canrig_jax.autorig._weld import clumps, weld
from canrig_jax.mesh import flipped_triangles


@pytest.fixture(scope="module")
def head(data_dir):
    return load_rocketbox_head("Male_Adult_08", data_dir)


def _skin_edges(head):
    f = head.faces[head.skin[head.faces].all(axis=1)]
    e = np.unique(np.sort(np.r_[f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1), axis=0)
    return e, np.linalg.norm(head.vertices[e[:, 0]] - head.vertices[e[:, 1]], axis=1)


@pytest.mark.parametrize("tau", [0.1, 0.3])
def test_a_clump_is_exactly_the_vertices_joined_by_short_skin_edges(head, tau):
    labels = clumps(head.vertices, head.faces, head.skin, tau)
    edges, length = _skin_edges(head)
    short = edges[length < tau * np.median(length)]
    assert len(short) > 0  # the crop has such clumps
    # every short skin edge joins one clump ...
    assert (labels[short[:, 0]] == labels[short[:, 1]]).all()
    # ... and every clump is held together by short edges alone: flood each from one vertex
    for label in np.unique(labels[short.ravel()]):
        members = set(np.flatnonzero(labels == label))
        reached, frontier = set(), [min(members)]
        while frontier:
            v = frontier.pop()
            if v not in reached:
                reached.add(v)
                frontier += list(short[short[:, 0] == v, 1]) + list(short[short[:, 1] == v, 0])
        assert reached == members
    # off the skin (eyes, teeth) and with tau = 0, every vertex is on its own
    assert len(np.unique(labels[~head.skin])) == (~head.skin).sum()
    off = clumps(head.vertices, head.faces, head.skin, 0.0)
    assert len(np.unique(off)) == len(head.vertices)


def test_a_welded_clump_translates_as_one_and_keeps_its_triangles_facing(head):
    labels = clumps(head.vertices, head.faces, head.skin, 0.3)
    rng = np.random.default_rng(0)
    d = rng.normal(scale=0.2, size=(3, len(head.vertices), 3)).astype(np.float32)
    welded = weld(d, labels)
    for label in np.unique(labels):  # an independent computation: one clump at a time
        members = np.flatnonzero(labels == label)
        want = d[:, members].astype(np.float64).mean(axis=1, keepdims=True)
        want = np.broadcast_to(want, welded[:, members].shape)
        np.testing.assert_allclose(welded[:, members], want, atol=1e-6)
    alone = np.bincount(labels)[labels] == 1
    np.testing.assert_array_equal(welded[:, alone], d[:, alone])
    # triangles wholly inside a clump turn over under noise larger than themselves, never welded
    inside = (labels[head.faces] == labels[head.faces[:, :1]]).all(axis=1)
    assert inside.sum() > 0
    frames = head.vertices[None] + np.concatenate([d, welded])
    flipped = flipped_triangles(frames, head.vertices, head.faces, mask=inside)
    assert flipped[:3].any() and not flipped[3:].any()


def test_bad_input_is_named(head):
    # shapes are checked by the annotations under the tests' type checker, else by the code
    mismatch = (ValueError, jaxtyping.TypeCheckError)
    with pytest.raises(ValueError, match="tau"):
        clumps(head.vertices, head.faces, head.skin, 1.5)
    with pytest.raises(mismatch, match="skin"):
        clumps(head.vertices, head.faces, head.skin[:-1], 0.1)
    with pytest.raises(mismatch, match="displacements"):
        weld(np.zeros((2, 5, 3)), np.arange(6))
