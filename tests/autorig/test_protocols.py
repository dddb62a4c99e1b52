"""The auto-rigging protocol pieces the experiments use: a head cut below the chin, and the
deformation-transfer base kept on disk between runs."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.autorig import (
    CHIN_LANDMARK,
    RiggedHead,
    _protocols,
    cached_transfer,
    crop_below_chin,
)


def _grid_head(rows: int = 6, cols: int = 4, poses: int = 3) -> RiggedHead:
    """A planar grid in x-y (cm, y up one per row), two triangles per cell, the chin landmark
    at the middle row; displacements and parts encode each vertex's index."""
    y, x = np.meshgrid(np.arange(rows, dtype=float), np.arange(cols, dtype=float), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    faces = []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a, b, d, e = r * cols + c, r * cols + c + 1, (r + 1) * cols + c, (r + 1) * cols + c + 1
            faces += [[a, b, e], [a, e, d]]
    n = vertices.shape[0]
    landmarks = np.arange(68) % n
    landmarks[CHIN_LANDMARK] = 3 * cols + 1  # row 3: y = 3 cm
    displacements = np.arange(poses)[:, None, None] * 100.0 + np.arange(n)[None, :, None]
    return RiggedHead(
        name="id00/grid",
        vertices=vertices,
        faces=np.asarray(faces, np.int32),
        displacements=np.repeat(displacements, 3, axis=2),
        landmarks=landmarks,
        parts=np.arange(n, dtype=np.int32),
        identity=np.zeros(2),
        topology="grid",
    )


@pytest.mark.parametrize("margin_cm, lowest_row", [(1.0, 3), (0.5, 3), (1.5, 2), (2.5, 1)])
def test_crop_below_chin_keeps_the_triangles_above_chin_minus_margin(margin_cm, lowest_row):
    head = _grid_head()
    cut, kept = crop_below_chin(head, margin_cm)
    rows = head.vertices[:, 1]
    # a triangle is kept when all its corners lie strictly above chin - margin: whole rows
    np.testing.assert_array_equal(kept, rows >= lowest_row)
    assert cut.name == "id00/grid/cut_below_chin"
    np.testing.assert_array_equal(cut.vertices, head.vertices[kept])
    np.testing.assert_array_equal(cut.parts, np.flatnonzero(kept))  # parts were the indices
    np.testing.assert_array_equal(cut.displacements, head.displacements[:, kept])
    # the faces are the kept ones, re-indexed: the same corner positions
    lowest = head.vertices[head.faces][:, :, 1].min(axis=1)
    np.testing.assert_array_equal(
        cut.vertices[cut.faces], head.vertices[head.faces[lowest >= lowest_row]]
    )
    # the chin landmark still names the same point
    np.testing.assert_array_equal(
        cut.vertices[cut.landmarks[CHIN_LANDMARK]], head.vertices[head.landmarks[CHIN_LANDMARK]]
    )


def test_crop_below_chin_refuses_a_margin_that_is_not_positive():
    for margin_cm in (-1.0, 0.0, float("nan")):
        with pytest.raises(ValueError, match="margin_cm"):
            crop_below_chin(_grid_head(), margin_cm)


def test_cached_transfer_reads_back_what_it_stored(tmp_path, monkeypatch):
    """The transfer is computed once per head and kind and read back after; a stored array of
    another shape (another remeshing under the same name) is recomputed; no cache: always."""
    calls = []

    def transfer(dataset, head, correspondence=None, *, static_below=None, anchor="vertex"):
        calls.append((head.name, static_below, anchor))
        scale = 1.0 if static_below is None else 2.0
        return head.displacements * scale  # float64: returned as float32

    monkeypatch.setattr(_protocols, "transfer_poses", transfer)
    head = _grid_head()
    first = cached_transfer(None, head, tmp_path / "cache", seed=0)
    assert first.dtype == np.float32
    np.testing.assert_array_equal(first, head.displacements.astype(np.float32))
    again = cached_transfer(None, head, tmp_path / "cache", seed=0)
    np.testing.assert_array_equal(again, first)
    assert len(calls) == 1
    # the kinds are stored apart: anchored, anchored per part, another seed
    anchored = cached_transfer(None, head, tmp_path / "cache", 0, static_below=0.05)
    np.testing.assert_array_equal(anchored, 2 * first)
    cached_transfer(None, head, tmp_path / "cache", 0, static_below=0.05, anchor="part")
    cached_transfer(None, head, tmp_path / "cache", 1)
    assert len(calls) == 4 and len(list((tmp_path / "cache").glob("*.npy"))) == 4
    np.testing.assert_array_equal(
        cached_transfer(None, head, tmp_path / "cache", 0, static_below=0.05), anchored
    )
    assert len(calls) == 4
    # the same name with another vertex count: recomputed
    other = _grid_head(rows=5)
    np.testing.assert_array_equal(
        cached_transfer(None, other, tmp_path / "cache", 0), other.displacements
    )
    assert len(calls) == 5
    cached_transfer(None, head, None, 0)
    cached_transfer(None, head, None, 0)
    assert len(calls) == 7
