"""Heads sculpted by other people with their artist's ARKit shapes: a ``SculptedHead`` checks
its shapes and finds its skin, and the Rocketbox heads of the data folder load with theirs."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.autorig import load_rocketbox_head
from canrig_jax.autorig._rocketbox import SculptedHead

NAMES = ("jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp", "mouthFunnel", "cheekPuff")


def _head() -> SculptedHead:
    """Two components (cm): a 5 x 5 grid (the skin) and a separate triangle; each shape moves
    the grid by random amounts and the triangle not at all."""
    y, x = np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(25)], axis=1)
    faces = [[r * 5 + c, r * 5 + c + 1, r * 5 + c + 6] for r in range(4) for c in range(4)]
    faces += [[r * 5 + c, r * 5 + c + 6, r * 5 + c + 5] for r in range(4) for c in range(4)]
    vertices = np.concatenate([grid, [[10, 0, 0], [11, 0, 0], [10, 1, 0]]])
    faces = np.asarray(faces + [[25, 26, 27]], np.int32)
    deltas = np.zeros((len(NAMES), 28, 3))
    deltas[:, :25] = np.random.default_rng(0).normal(0, 0.1, (len(NAMES), 25, 3))
    return SculptedHead("head", vertices, faces, deltas, NAMES)


def test_a_sculpted_head_checks_its_shapes_and_finds_its_skin():
    head = _head()
    assert head.skin.sum() == 25 and not head.skin[25:].any()
    np.testing.assert_array_equal(head.shapes(["eyeBlinkLeft"])[0], head.deltas[2])
    with pytest.raises(ValueError, match="deltas"):
        SculptedHead("bad", head.vertices, head.faces, head.deltas[:3], NAMES)


def test_a_rocketbox_head_has_its_artists_shapes(data_dir):
    head = load_rocketbox_head("Female_Adult_01", data_dir)
    assert head.deltas.shape == (len(head.names), len(head.vertices), 3)
    assert {"jawOpen", "eyeBlinkLeft", "browInnerUp"} <= set(head.names)
    assert 0 < head.skin.sum() < len(head.vertices)
    jaw = np.linalg.norm(head.shapes(["jawOpen"])[0], axis=-1)
    assert jaw[head.skin].max() > 0.5  # cm: the jaw opens by more than 5 mm somewhere
