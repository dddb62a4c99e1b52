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


@pytest.mark.parametrize(("units", "size"), [("mm", "0.376"), ("cm", "3.76"), ("m", "376")])
def test_a_stated_unit_that_makes_no_head_is_refused(makehuman, tmp_path, units, size):
    """MakeHuman's head is in decimetres: stated in any other unit it is 0.4 cm to 3.8 m
    tall, refused (never a rig that size), naming the file, the argument and the unit."""
    vertices, faces = makehuman
    path = save_obj(tmp_path / "head.obj", vertices, faces)
    with pytest.raises(
        ValueError, match=rf"units: .*head.obj is {size} cm tall .*units='{units}'.*units='dm'"
    ):
        load_head(path, units=units)
    head = load_head(path, units="dm")
    assert head.units == "dm" and not head.inferred and head.size_cm == pytest.approx(37.6, abs=0.1)


def test_the_plausible_range_is_10_to_60_cm(makehuman, tmp_path):
    """A stated unit is accepted from 10 to 60 cm (wider than inference's 15-45 cm): a face
    mask 12 cm tall, a head and shoulders 55 cm; 9 and 61 cm are refused."""
    vertices, faces = makehuman
    extent = float(np.ptp(vertices, axis=0).max())
    for size_cm, accepted in ((12.0, True), (55.0, True), (9.0, False), (61.0, False)):
        path = save_obj(tmp_path / f"h{size_cm:g}.obj", vertices * (size_cm / extent), faces)
        if accepted:
            assert load_head(path, units="cm").size_cm == pytest.approx(size_cm, rel=1e-5)
        else:
            with pytest.raises(ValueError, match=f"h{size_cm:g}.obj is {size_cm:g} cm tall"):
                load_head(path, units="cm")


def test_stated_units_checked(makehuman, tmp_path):
    vertices, faces = makehuman
    path = save_obj(tmp_path / "head.obj", vertices, faces)
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
