"""FBX in: meshes, blend shapes, unit and axes; rigs from FBX; bad FBX files.

The Rocketbox heads in the data folder were cut out of the same FBX files independently
(``rocketbox.json``): the loader must give their neutral, deltas and faces back. Small
ASCII FBX files written here check the unit, axes, node transform, fan split and mesh choice
against positions computed by hand.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from canrig_jax import CorruptFileError
from canrig_jax.data import ARKIT_NAMES, arkit_name_of, load_fbx, load_head
from canrig_jax.data._fbx import load_fbx_meshes
from canrig_jax.rig import load_fbx_rig

HEADS = ("Female_Adult_01", "Male_Adult_08")
JAW_OPEN_MAX_CM = {"Female_Adult_01": 1.7, "Male_Adult_08": 1.9}
"""jawOpen's largest displacement (the data folder's README)."""


@pytest.fixture(scope="module", params=HEADS)
def rocketbox(request, data_dir):
    """(name, FBX path, head crop npz arrays) of one Rocketbox head; skips without the files."""
    fbx = data_dir / "rocketbox" / f"{request.param}_facial.fbx"
    npz = data_dir / "rocketbox" / f"{request.param}_head.npz"
    if not (fbx.is_file() and npz.is_file()):
        pytest.skip(f"the data folder has no {fbx.name} / {npz.name}")
    with np.load(npz) as z:
        crop = {k: z[k] for k in z.files}
    return request.param, fbx, crop


@pytest.fixture(scope="module")
def rocketbox_mesh(rocketbox):
    """``load_fbx`` of the head's FBX file (read once per head: a load takes ~0.5 s)."""
    return load_fbx(rocketbox[1])


@pytest.fixture(scope="module")
def rocketbox_head_rig(rocketbox):
    """``load_fbx_rig(crop="head")`` of the head's FBX file."""
    return load_fbx_rig(rocketbox[1], crop="head")


# ------------------------------------------------------------------------- a small FBX writer
def ascii_fbx(
    meshes: list[dict], *, up=(2, 1), front=(1, -1), coord=(0, 1), unit_scale_cm=100.0
) -> str:
    """An ASCII FBX 7.4 file: ``meshes`` are dicts with ``name``, ``vertices`` (xyz rows),
    ``polygons`` (index lists) and optionally ``translation`` and ``shapes`` ({name:
    (indices, offsets)}). Axes as FBX's GlobalSettings (axis, sign); the default is 3ds Max's
    z up, right-handed, in metres (``UnitScaleFactor`` 100)."""
    out = ["; FBX 7.4.0 project file", "FBXHeaderExtension:  {", "\tFBXVersion: 7400", "}"]
    out += ["GlobalSettings:  {", "\tVersion: 1000", "\tProperties70:  {"]
    for key, (axis, sign) in (("Up", up), ("Front", front), ("Coord", coord)):
        out.append(f'\t\tP: "{key}Axis", "int", "Integer", "",{axis}')
        out.append(f'\t\tP: "{key}AxisSign", "int", "Integer", "",{sign}')
    out += [f'\t\tP: "UnitScaleFactor", "double", "Number", "",{unit_scale_cm!r}', "\t}", "}"]
    out.append("Objects:  {")
    links, uid = [], 1000

    def array(key, values):
        return [f"\t\t{key}: *{len(values)} {{", "\t\t\ta: " + ",".join(map(repr, values)), "\t\t}"]

    for m in meshes:
        geometry, model = uid + 1, uid + 2
        uid += 2
        corners = []
        for polygon in m["polygons"]:
            corners += [*polygon[:-1], -polygon[-1] - 1]  # FBX ends a polygon with ~index
        out.append(f'\tGeometry: {geometry}, "Geometry::{m["name"]}", "Mesh" {{')
        out += array("Vertices", [float(c) for v in m["vertices"] for c in v])
        out += array("PolygonVertexIndex", corners) + ["\t}"]
        t = ",".join(repr(float(c)) for c in m.get("translation", (0, 0, 0)))
        out += [f'\tModel: {model}, "Model::{m["name"]}", "Mesh" {{', "\t\tProperties70:  {"]
        out += [f'\t\t\tP: "Lcl Translation", "Lcl Translation", "", "A",{t}', "\t\t}", "\t}"]
        links += [(model, 0), (geometry, model)]
        if m.get("shapes"):
            blend = uid = uid + 1
            out += [f'\tDeformer: {blend}, "Deformer::{m["name"]}Shapes", "BlendShape" {{', "\t}"]
            links.append((blend, geometry))
            for name, (index, offsets) in m["shapes"].items():
                channel, shape = uid + 1, uid + 2
                uid += 2
                out += [f'\tDeformer: {channel}, "SubDeformer::{name}", "BlendShapeChannel" {{']
                out += array("FullWeights", [100.0]) + ["\t}"]
                out += [f'\tGeometry: {shape}, "Geometry::{name}", "Shape" {{']
                out += array("Indexes", list(index))
                out += array("Vertices", [float(c) for v in offsets for c in v]) + ["\t}"]
                links += [(channel, blend), (shape, channel)]
    out += ["}", "Connections:  {"] + [f'\tC: "OO",{a},{b}' for a, b in links] + ["}"]
    return "\n".join(out) + "\n"


# A unit square (a quad) and a pentagon beside it, z up in metres, 0.5 m up, with a shape.
SQUARE = {
    "name": "face",
    "vertices": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, -0.5, 0), (3, 0, 0), (3, 1, 0)],
    "polygons": [(0, 1, 2, 3), (1, 4, 5, 6, 2)],
    "translation": (0, 0, 0.5),
    "shapes": {"AK_25_JawOpen": ([2, 6], [(0, 0, -0.01), (0.02, 0, 0)])},
}


def _z_up_metres_to_cm_y_up(p):
    """(x, y, z) in metres, z up, front -y -> (x, z, -y) in cm: the README's conversion."""
    p = np.asarray(p, np.float64)
    return 100.0 * np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def test_unit_axes_and_node_transform_from_the_file(tmp_path):
    path = tmp_path / "square.fbx"
    path.write_text(ascii_fbx([SQUARE]))
    mesh = load_fbx(path)
    source = np.asarray(SQUARE["vertices"], np.float64) + SQUARE["translation"]
    np.testing.assert_allclose(mesh.vertices, _z_up_metres_to_cm_y_up(source), atol=1e-4)
    assert mesh.unit_cm == pytest.approx(100.0) and mesh.axes == ("+x", "+z", "-y")
    # fan split in polygon order: quad (0,1,2,3), pentagon (1,4,5,6,2)
    expected = [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 6], [1, 6, 2]]
    np.testing.assert_array_equal(mesh.triangles, expected)
    assert mesh.names == ("AK_25_JawOpen",)
    dense = np.zeros((7, 3))
    dense[2], dense[6] = (0, 0, -0.01), (0.02, 0, 0)
    np.testing.assert_allclose(mesh.deltas[0], _z_up_metres_to_cm_y_up(dense), atol=1e-5)
    # the shape lowers vertex 2 by 1 cm along -y (z up became y up)
    assert mesh.deltas[0, 2, 1] == pytest.approx(-1.0, abs=1e-5)


def test_left_handed_axes_mirror_and_keep_triangles_facing_out(tmp_path):
    """CoordAxisSign -1 (right = -x) mirrors x: positions follow it and the winding flips,
    so each triangle's normal is the mirrored normal of the source triangle."""
    path = tmp_path / "mirror.fbx"
    path.write_text(ascii_fbx([SQUARE], up=(1, 1), front=(2, 1), coord=(0, -1), unit_scale_cm=1))
    mesh = load_fbx(path)
    source = np.asarray(SQUARE["vertices"], np.float64) + SQUARE["translation"]
    mirror = np.diag([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(mesh.vertices, source @ mirror.T, atol=1e-5)
    v = mesh.vertices.astype(np.float64)
    normals = np.cross(
        v[mesh.triangles[:, 1]] - v[mesh.triangles[:, 0]],
        v[mesh.triangles[:, 2]] - v[mesh.triangles[:, 0]],
    )
    # the source triangles face +z and the mirror M keeps z: M n = +z. Mirroring the
    # positions with the winding kept would turn them inside out (normal -M n = -z).
    assert np.all(normals[:, 2] > 0)


def test_mesh_choice_by_name_and_by_shape_count(tmp_path):
    other = {"name": "eyes", "vertices": [(0, 0, 0), (1, 0, 0), (0, 1, 0)], "polygons": [(0, 1, 2)]}
    path = tmp_path / "two.fbx"
    path.write_text(ascii_fbx([other, SQUARE]))
    assert load_fbx(path).name == "face"  # the one with blend shapes
    eyes = load_fbx(path, mesh="eyes")
    assert eyes.name == "eyes" and eyes.n_blendshapes == 0 and eyes.deltas.shape == (0, 3, 3)
    assert eyes.meshes == ("eyes", "face") == tuple(m.name for m in load_fbx_meshes(path))
    with pytest.raises(ValueError, match=r"mesh: .*two.fbx has no mesh 'teeth'.*'eyes'.*'face'"):
        load_fbx(path, mesh="teeth")
    tie = tmp_path / "tie.fbx"
    tie.write_text(ascii_fbx([other, {**other, "name": "lashes"}]))
    with pytest.raises(ValueError, match=r"tie.fbx holds 2 meshes with 0 blend shapes.*mesh="):
        load_fbx(tie)


def test_bad_fbx_files_named_before_any_work(tmp_path, data_dir):
    with pytest.raises(FileNotFoundError, match="nothere.fbx"):
        load_fbx(tmp_path / "nothere.fbx")
    (tmp_path / "empty.fbx").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.fbx is empty"):
        load_fbx(tmp_path / "empty.fbx")
    (tmp_path / "notes.fbx").write_text("these are notes\n")
    with pytest.raises(ValueError, match="notes.fbx is not an FBX file"):
        load_fbx(tmp_path / "notes.fbx")
    with pytest.raises(ValueError, match="is not a file"):
        load_fbx(tmp_path)
    with pytest.raises(TypeError, match="path"):
        load_fbx(3)
    source = data_dir / "rocketbox" / "Male_Adult_08_facial.fbx"
    if not source.is_file():
        pytest.skip("the data folder has no Rocketbox FBX")
    data = source.read_bytes()
    for name, cut in (
        ("half.fbx", len(data) // 2),
        ("header.fbx", 24),
        ("end.fbx", len(data) - 400),
    ):
        (tmp_path / name).write_bytes(data[:cut])
        with pytest.raises(CorruptFileError, match=name):
            load_fbx(tmp_path / name)


# ------------------------------------------------------------------------ the Rocketbox heads
def test_round_trip_against_the_head_crop(rocketbox, rocketbox_mesh):
    """The crop's vertices (``orig_vertex_index``) and its 52 ARKit deltas, by name."""
    _, _, crop = rocketbox
    mesh = rocketbox_mesh
    index = crop["orig_vertex_index"]
    np.testing.assert_allclose(mesh.vertices[index], crop["neutral"], rtol=0, atol=2e-5)
    by_arkit = {arkit_name_of(n): i for i, n in enumerate(mesh.names) if arkit_name_of(n)}
    assert sorted(by_arkit) == sorted(ARKIT_NAMES) == sorted(str(n) for n in crop["names"])
    ours = mesh.deltas[[by_arkit[str(n)] for n in crop["names"]]]
    np.testing.assert_allclose(ours[:, index], crop["deltas"], rtol=0, atol=1e-5)
    outside = np.delete(ours, index, axis=1)
    assert np.abs(outside).max() < 1e-3  # nothing the crop left out moves


def test_rig_head_crop_is_the_data_folders_crop(rocketbox, rocketbox_head_rig):
    """``crop="head"`` makes the same head as the data folder's independent crop: same
    vertices in the same order, the same fan-split faces, the same deltas by name."""
    _, _, crop = rocketbox
    rig = rocketbox_head_rig
    assert rig.units == "cm" and rig.n_blendshapes == 52 and set(rig.names) == set(ARKIT_NAMES)
    np.testing.assert_allclose(rig.neutral, crop["neutral"], rtol=0, atol=2e-5)
    np.testing.assert_array_equal(rig.faces, crop["faces"])
    order = rig.index([str(n) for n in crop["names"]])
    np.testing.assert_allclose(np.asarray(rig.deltas)[order], crop["deltas"], rtol=0, atol=1e-5)


def test_centimetres_y_up_facing_plus_z(rocketbox, rocketbox_mesh, rocketbox_head_rig):
    """Invariants of the conversion: a standing adult 1.5-2 m tall along +y, jawOpen moves
    the chin down by the README's amount, the face is in front (+z) of the head."""
    who, _, _ = rocketbox
    mesh = rocketbox_mesh
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    assert 150 < extent[1] < 200 and extent[1] == extent.max()
    assert mesh.vertices[:, 1].min() > -5  # feet at the floor, y up (not down)
    jaw = mesh.deltas[mesh.names.index("AK_25_JawOpen")]
    size = np.linalg.norm(jaw, axis=1)
    assert size.max() == pytest.approx(JAW_OPEN_MAX_CM[who], abs=0.05)
    assert jaw[size > 0.5 * size.max(), 1].mean() < -0.5 * size.max()  # down, along -y
    rig = rocketbox_head_rig
    head = np.asarray(rig.neutral)
    moving = np.linalg.norm(np.asarray(rig.deltas)[rig.index(["jawOpen"])[0]], axis=1) > 0.1
    assert head[moving, 2].mean() > head[:, 2].mean() + 3  # the mouth is at the front
    assert 20 < np.ptp(head[:, 1]) < 40  # a head with some neck, in cm


def test_rig_names(rocketbox, rocketbox_mesh, rocketbox_head_rig):
    """``names="all"``: every shape, ARKit ones renamed; the default keeps the ARKit ones in
    file order (the head rig, cropped to the data folder's crop)."""
    _, path, crop = rocketbox
    every = load_fbx_rig(path, names="all")
    assert every.n_blendshapes == 175
    expected = [arkit_name_of(n) or n for n in rocketbox_mesh.names]
    assert list(every.names) == expected and "AA_VI_00_Sil" in every.names
    np.testing.assert_array_equal(every.deltas, rocketbox_mesh.deltas)
    arkit = rocketbox_head_rig
    assert arkit.names == tuple(n for n in every.names if n in ARKIT_NAMES)
    every_on_crop = np.asarray(every.deltas)[every.index(arkit.names)][:, crop["orig_vertex_index"]]
    np.testing.assert_array_equal(arkit.deltas, every_on_crop)
    with pytest.raises(ValueError, match="names: expected one of"):
        load_fbx_rig(path, names="arkit")
    with pytest.raises(ValueError, match="crop: expected one of"):
        load_fbx_rig(path, crop="face")


def test_rig_name_clash_and_no_arkit_shapes(tmp_path):
    clash = dict(
        SQUARE, shapes={"AK_25_JawOpen": ([2], [(0, 0, -1)]), "JawOpen": ([2], [(0, 0, -2)])}
    )
    (tmp_path / "clash.fbx").write_text(ascii_fbx([clash]))
    with pytest.raises(ValueError, match="several shapes for one ARKit name.*jawOpen"):
        load_fbx_rig(tmp_path / "clash.fbx")
    visemes = dict(SQUARE, shapes={"AA_VI_01_PP": ([2], [(0, 0, -1)])})
    (tmp_path / "visemes.fbx").write_text(ascii_fbx([visemes]))
    with pytest.raises(ValueError, match="no ARKit blend shape.*names='all'"):
        load_fbx_rig(tmp_path / "visemes.fbx")
    assert load_fbx_rig(tmp_path / "visemes.fbx", names="all").names == ("AA_VI_01_PP",)


# ---------------------------------------------------------------------------- load_head
def test_load_head_reads_fbx_in_cm_y_up(tmp_path):
    """A head-sized FBX (metres, z up, two meshes): concatenated, converted, ``units="cm"``;
    ``units=`` reads the file's numbers in another unit."""
    head = {
        "name": "head",
        "vertices": [(0, 0, 0), (0.2, 0, 0), (0, 0, 0.3)],
        "polygons": [(0, 1, 2)],
    }
    eye = {
        "name": "eye",
        "vertices": [(0, 0, 0.1), (0.01, 0, 0.1), (0, 0.01, 0.1)],
        "polygons": [(0, 1, 2)],
    }
    path = tmp_path / "head.fbx"
    path.write_text(ascii_fbx([head, eye]))
    mesh = load_head(path)
    assert mesh.units == "cm" and not mesh.inferred and mesh.size_cm == pytest.approx(30)
    both = np.concatenate([head["vertices"], eye["vertices"]])
    np.testing.assert_allclose(mesh.vertices, _z_up_metres_to_cm_y_up(both), atol=1e-4)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [3, 4, 5]])
    in_m = load_head(path, units="m")  # the file's own numbers, read in the stated unit
    assert in_m.units == "m" and in_m.size_cm == pytest.approx(30)
    np.testing.assert_allclose(in_m.vertices, _z_up_metres_to_cm_y_up(both) / 100, atol=1e-6)
    with pytest.raises(ValueError, match=r"units: .*head.fbx is 0.03 cm tall.*units='m'"):
        load_head(path, units="mm")


def test_load_head_refuses_a_whole_body_fbx(data_dir):
    path = data_dir / "rocketbox" / "Male_Adult_08_facial.fbx"
    if not path.is_file():
        pytest.skip(f"the data folder has no {path.name}")
    with pytest.raises(ValueError, match=rf"{path.name} is 1\d\d cm tall .*crop the file"):
        load_head(path)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX shell scripts stand in for Python")
@pytest.mark.parametrize(
    ("script", "error", "match"),
    [
        ("kill -SEGV $$", CorruptFileError, r"reader stopped on .*square.fbx \(exit status -11"),
        ("echo \"No module named 'ufbx'\" >&2; exit 4", ImportError, "pip install ufbx"),
        ("echo 'UnknownError: Failed to load' >&2; exit 3", CorruptFileError, "Failed to load"),
    ],
)
def test_a_reader_that_dies_is_an_error_naming_the_file(
    tmp_path, monkeypatch, script, error, match
):
    """The ufbx reader runs in a child process: a crash, a missing ufbx or ufbx's refusal
    there is a Python error here (the caller's process is never the one that crashes)."""
    path = tmp_path / "square.fbx"
    path.write_text(ascii_fbx([SQUARE]))
    fake = tmp_path / "python"
    fake.write_text(f"#!/bin/sh\n{script}\n")
    fake.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(fake))
    with pytest.raises(error, match=match):
        load_fbx(path)
