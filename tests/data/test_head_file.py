"""Head files in: OBJ, PLY, GLB through trimesh; units given or inferred; bad files."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from canrig_jax.data import data_file, load_head, read_arrays, save_obj


@pytest.fixture(scope="module")
def makehuman(data_dir):
    """The MakeHuman hm08 head crop (decimetres), evaluation data."""
    z = read_arrays(data_file("makehuman/hm08_face.npz", data_dir), ("neutral", "faces"))
    return z["neutral"], z["faces"]


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb", ".gltf"])
def test_formats_round_trip_and_units_inferred(makehuman, tmp_path, suffix):
    vertices, faces = makehuman
    path = tmp_path / f"head{suffix}"
    if suffix == ".obj":
        save_obj(path, vertices, faces)
    else:
        trimesh.Trimesh(vertices, faces, process=False).export(path)
    head = load_head(path)
    assert head.units == "dm" and head.inferred  # MakeHuman's decimetres, from the box
    assert head.faces.shape == faces.shape
    np.testing.assert_array_equal(head.faces, faces)
    np.testing.assert_allclose(head.vertices, vertices, atol=1e-6)
    assert head.size_cm == pytest.approx(37.6, abs=0.1)
    np.testing.assert_allclose(head.vertices_in("cm"), vertices * 10, rtol=1e-6, atol=1e-5)


def test_stated_units_checked(makehuman, tmp_path):
    vertices, faces = makehuman
    path = save_obj(tmp_path / "head.obj", vertices, faces)
    with pytest.warns(UserWarning, match="3.76 cm, not a human head's 15-45 cm.*in dm"):
        head = load_head(path, units="cm")
    assert head.units == "cm" and not head.inferred
    save_obj(tmp_path / "tiny.obj", vertices * 1e-4, faces)
    with pytest.raises(ValueError, match="tiny.obj spans.*give the units"):
        load_head(tmp_path / "tiny.obj")
    with pytest.raises(ValueError, match="units: expected one of"):
        load_head(path, units="inch")


def test_bad_head_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.obj"):
        load_head(tmp_path / "nothere.obj")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(ValueError, match="empty.obj is empty"):
        load_head(tmp_path / "empty.obj")
    (tmp_path / "notes.obj").write_text("these are notes, not a mesh\n")
    with pytest.raises(ValueError, match="notes.obj"):
        load_head(tmp_path / "notes.obj")
    (tmp_path / "junk.glb").write_bytes(os.urandom(64))
    with pytest.raises(ValueError, match="junk.glb"):
        load_head(tmp_path / "junk.glb")
    (tmp_path / "head.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(ValueError, match="head.stl has extension"):
        load_head(tmp_path / "head.stl")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="points.obj holds no triangle mesh"):
        load_head(tmp_path / "points.obj")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(NotADirectoryError, match="afile"):
        save_obj(tmp_path / "afile" / "head.obj", np.zeros((3, 3)), np.array([[0, 1, 2]]))
