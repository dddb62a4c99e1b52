"""Whole avatars in, the same avatars with a face rig out (``autorig.auto_rig_avatar``,
``canrig autorig AVATAR``, ``rig.add_morph_targets``, ``rig.avatar_from_fbx``).

The test avatar is built here from the data folder: the Rocketbox male head (its skin and two
eyes as three meshes) under a small skeleton (hips, spine, neck, head), with a skinned body
box, a hair card skinned to the head, a textured material and a head-turn animation, written
by this file's own GLB writer (not the package's). Most tests run ``auto_rig_avatar`` with a
stand-in for ``auto_rig`` whose shapes are a closed form of the vertices' world positions, so
that where the targets land (which meshes, which frame, which units) is checked exactly in a
second; the real rig runs on both Rocketbox FBX bodies.
"""

from __future__ import annotations

import copy
import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from canrig_jax import autorig, run_command
from canrig_jax.autorig import Check, RigCheck
from canrig_jax.autorig._avatar import find_head_node
from canrig_jax.data import data_file, load_fbx, load_fbx_scene, read_arrays
from canrig_jax.rig import (
    EXTRA_SHAPES,
    BlendshapeRig,
    accessor_array,
    add_morph_targets,
    avatar_from_fbx,
    find_gltf_validator,
    mesh_vertices,
    read_gltf_avatar,
    validate_gltf,
    write_gltf_avatar,
)

ROCKETBOX = ("Male_Adult_08", "Female_Adult_01")
HEAD_NODE, EYE_NODES = 4, (5, 6)
MESHES = ("Body", "HeadSkin", "EyeLeft", "EyeRight", "Hair")


def _png() -> bytes:
    """A valid 2 x 2 PNG (the avatar's texture)."""
    import io

    import matplotlib.image

    out = io.BytesIO()
    matplotlib.image.imsave(out, np.full((2, 2, 3), 0.8), format="png")
    return out.getvalue()


# ------------------------------------------------------------------ an independent GLB writer
class _Glb:
    def __init__(self):
        self.blob, self.views, self.accessors = bytearray(), [], []

    def add(self, array, component, kind, bounds=False):
        while len(self.blob) % 4:
            self.blob.append(0)
        array = np.ascontiguousarray(array)
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": array.nbytes})
        self.blob.extend(array.tobytes())
        accessor = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": len(array),
            "type": kind,
        }
        if bounds:
            accessor["min"] = array.min(axis=0).tolist()
            accessor["max"] = array.max(axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def raw(self, data: bytes) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)})
        self.blob.extend(data)
        return len(self.views) - 1

    def write(self, path, document):
        while len(self.blob) % 4:
            self.blob.append(0)
        document = {
            **document,
            "buffers": [{"byteLength": len(self.blob)}],
            "bufferViews": self.views,
            "accessors": self.accessors,
        }
        text = json.dumps(document).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text
        body += struct.pack("<II", len(self.blob), 0x004E4942) + bytes(self.blob)
        path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
        return path


def _box(centre, size):
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    vertices = (corners - 0.5) * size + centre
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return vertices.astype(np.float32), np.asarray(faces, np.uint32)


def build_avatar(path, data_dir, *, head_name="Head", extra_head=False, grid=0):
    """A small whole-body avatar in metres (module docstring); returns the head's parts."""
    head = read_arrays(
        data_file("rocketbox/Male_Adult_08_head.npz", data_dir),
        ("neutral", "faces", "component_labels"),
    )
    cm, labels = head["neutral"].astype(np.float64), head["component_labels"]
    world = cm / 100.0 + np.array([0.0, 1.55 - cm[:, 1].min() / 100.0, 0.0])
    joints_world = {1: (0.0, 1.0, 0.0), 2: (0.0, 1.3, 0.0), 3: (0.0, 1.5, 0.0), 4: (0.0, 1.6, 0.0)}
    glb = _Glb()
    meshes, nodes = (
        [],
        [
            {"name": "Armature", "children": [1]},
            {"name": "Hips", "translation": [0.0, 1.0, 0.0], "children": [2]},
            {"name": "Spine", "translation": [0.0, 0.3, 0.0], "children": [3]},
            {"name": "Neck", "translation": [0.0, 0.2, 0.0], "children": [4]},
            {"name": head_name, "translation": [0.0, 0.1, 0.0], "children": list(EYE_NODES)},
        ],
    )
    skin_joints = [1, 2, 3, 4]
    ibm = np.stack([np.eye(4) for _ in skin_joints])
    for k, j in enumerate(skin_joints):
        ibm[k, :3, 3] = -np.asarray(joints_world[j])
    ibm_accessor = glb.add(np.transpose(ibm, (0, 2, 1)).reshape(-1, 16).astype(np.float32),
                           5126, "MAT4")  # fmt: skip

    def skinned(name, vertices, faces, joint, extra=None):
        n = len(vertices)
        joints = np.zeros((n, 4), np.uint16)
        joints[:, 0] = joint
        weights = np.zeros((n, 4), np.float32)
        weights[:, 0] = 1.0
        attributes = {
            "POSITION": glb.add(vertices.astype(np.float32), 5126, "VEC3", True),
            "JOINTS_0": glb.add(joints, 5123, "VEC4"),
            "WEIGHTS_0": glb.add(weights, 5126, "VEC4"),
            **(extra or {}),
        }
        primitive = {"attributes": attributes, "indices": glb.add(faces.reshape(-1), 5125,
                     "SCALAR"), "mode": 4}  # fmt: skip
        meshes.append({"name": name, "primitives": [primitive]})
        return len(meshes) - 1

    body_v, body_f = _box(np.array([0.0, 1.15, 0.0]), np.array([0.3, 0.5, 0.2]))
    body = skinned("Body", body_v, body_f, joint=1)
    skin_index = np.flatnonzero(labels == 0)
    skin_faces = _sub_faces(head["faces"], skin_index)
    uv = glb.add(np.zeros((len(skin_index), 2), np.float32), 5126, "VEC2")
    head_mesh = skinned("HeadSkin", world[skin_index], skin_faces, joint=3,
                        extra={"TEXCOORD_0": uv})  # fmt: skip
    # weights on the neck for the lowest vertices: these stay out of the face
    low = world[skin_index, 1] < world[skin_index, 1].min() + 0.03
    joints_view = glb.accessors[meshes[head_mesh]["primitives"][0]["attributes"]["JOINTS_0"]]
    view = glb.views[joints_view["bufferView"]]
    joints = np.frombuffer(glb.blob, np.uint16, 4 * len(skin_index), view["byteOffset"])
    joints = joints.reshape(-1, 4).copy()
    joints[low, 0] = 2
    glb.blob[view["byteOffset"] : view["byteOffset"] + joints.nbytes] = joints.tobytes()
    meshes[head_mesh]["primitives"][0]["material"] = 0
    for label, name in zip((1, 2), ("EyeLeft", "EyeRight"), strict=True):
        index = np.flatnonzero(labels == label)
        centre = world[index].mean(axis=0)
        local = world[index] - centre
        primitive = {
            "attributes": {"POSITION": glb.add(local.astype(np.float32), 5126, "VEC3", True)},
            "indices": glb.add(_sub_faces(head["faces"], index).reshape(-1), 5125, "SCALAR"),
        }
        meshes.append({"name": name, "primitives": [primitive]})
        offset = (centre - np.asarray(joints_world[4])).tolist()
        nodes.append({"name": f"{name}Node", "translation": offset, "mesh": len(meshes) - 1})
    hair_v, hair_f = _box(world[skin_index].mean(axis=0) + [0.0, 0.12, 0.0], np.full(3, 0.05))
    hair = skinned("Hair", hair_v, hair_f, joint=3)
    nodes += [
        {"name": "BodyMesh", "mesh": body, "skin": 0},
        {"name": "HeadSkinMesh", "mesh": head_mesh, "skin": 0},
        {"name": "HairMesh", "mesh": hair, "skin": 0},
    ]
    if extra_head:  # a second, unrelated head
        nodes.append({"name": "Spare Head", "translation": [1.0, 0.0, 0.0]})
    if grid:  # a head-sized sheet of grid x grid vertices skinned to the head
        g = np.linspace(-0.1, 0.1, grid)
        x, y = np.meshgrid(g, g)
        sheet = np.stack([x.ravel(), y.ravel() + 1.7, np.zeros(grid * grid)], axis=1)
        i = np.arange(grid * grid).reshape(grid, grid)[:-1, :-1].ravel()
        faces = np.concatenate([np.stack([i, i + 1, i + grid], 1),
                                np.stack([i + 1, i + grid + 1, i + grid], 1)])  # fmt: skip
        nodes.append({"name": "SheetMesh", "mesh": skinned("Sheet", sheet, faces.astype(
            np.uint32), joint=3), "skin": 0})  # fmt: skip
    times = glb.add(np.array([[0.0], [1.0]], np.float32), 5126, "SCALAR", True)
    turn = glb.add(np.array([[0, 0, 0, 1], [0, 0.2588, 0, 0.9659]], np.float32), 5126, "VEC4")
    image_view = glb.raw(_png())
    roots = [0] + [i for i, n in enumerate(nodes) if n["name"].endswith(("Mesh", "Spare Head"))]
    document = {
        "asset": {"version": "2.0", "generator": "canrig_jax tests"},
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": nodes,
        "meshes": meshes,
        "skins": [{"joints": skin_joints, "inverseBindMatrices": ibm_accessor, "skeleton": 0}],
        "materials": [{"name": "skin", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{}],
        "images": [{"bufferView": image_view, "mimeType": "image/png"}],
        "animations": [
            {
                "name": "turn",
                "samplers": [{"input": times, "output": turn}],
                "channels": [{"sampler": 0, "target": {"node": HEAD_NODE, "path": "rotation"}}],
            }
        ],
    }
    if extra_head:  # a joint too, of a second skin
        document["skins"].append({"joints": [len(nodes) - 1 - (1 if grid else 0)]})
    glb.write(path, document)
    return world, labels


def _sub_faces(faces, index):
    new = np.full(faces.max() + 1, -1, np.int64)
    new[index] = np.arange(len(index))
    kept = faces[(new[faces] >= 0).all(axis=1)]
    return new[kept].astype(np.uint32)


def _closed_form(world_cm):
    """(3, V, 3) shapes of world positions (cm): a stand-in rig with exact expectations."""
    centre = world_cm.mean(axis=0)
    return np.stack(
        [
            np.tile([0.0, -1.0, 0.0], (len(world_cm), 1)),  # everything 1 cm down
            0.1 * (world_cm - centre),  # 10% larger about the centre
            np.tile([0.5, 0.0, 0.25], (len(world_cm), 1)),
        ]
    )


NAMES = ("jawOpen", "cheekPuff", "mouthLeft")


@pytest.fixture
def stand_in(monkeypatch):
    """``auto_rig`` replaced by the closed form; records what it was given."""
    calls = []

    class Result:
        method = "stand-in"

    def fake(vertices, faces, **options):
        calls.append((np.asarray(vertices), np.asarray(faces), options))
        result = Result()
        shapes = _closed_form(np.asarray(vertices, np.float64)).astype(np.float32)
        result.rig = BlendshapeRig(vertices, shapes, (), NAMES, faces)
        return result

    monkeypatch.setattr("canrig_jax.autorig._avatar.auto_rig", fake)
    monkeypatch.setattr("canrig_jax.autorig._avatar.check_auto_rig", lambda result: _report(True))
    return calls


def _report(ok: bool) -> RigCheck:
    """A ``RigCheck`` whose one hard check (``blink_closes``) passes or fails."""
    check = Check("blink_closes", 0.05 if ok else 0.4, 0.1, ok, True)
    empty = np.zeros(0, np.int64)
    return RigCheck((check,), np.zeros((0, 3), np.float32), "random sparse poses", empty, empty)


@pytest.fixture
def refuse_rig(monkeypatch):
    def fake(*args, **kwargs):
        raise AssertionError("auto_rig reached: the error must come before compiled work")

    monkeypatch.setattr("canrig_jax.autorig._avatar.auto_rig", fake)


@pytest.fixture(scope="module")
def avatar_file(tmp_path_factory, data_dir):
    path = tmp_path_factory.mktemp("avatar") / "avatar.glb"
    world, labels = build_avatar(path, data_dir)
    return path, world, labels


def _targets(avatar, mesh):
    primitive = avatar.document["meshes"][mesh]["primitives"][0]
    return np.stack([accessor_array(avatar, t["POSITION"]) for t in primitive["targets"]])


REPO = Path(__file__).resolve().parents[2]


def _three(path) -> dict:
    """What a three.js app sees in ``path`` (``tests/clients/load_avatar.mjs``: GLTFLoader with
    @pixiv/three-vrm's plugin, in Node)."""
    modules = REPO / "node_modules"
    if shutil.which("node") is None or not (modules / "@pixiv" / "three-vrm").is_dir():
        pytest.skip("Node.js or npm three / @pixiv/three-vrm missing: npm install three "
                    "@pixiv/three-vrm")  # fmt: skip
    done = subprocess.run(
        ["node", str(REPO / "tests" / "clients" / "load_avatar.mjs"), str(path)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _validate(path):
    if find_gltf_validator() is None:
        pytest.skip("Node.js or the npm package gltf-validator is missing")
    issues = validate_gltf(path)["issues"]
    assert issues["numErrors"] == 0, issues["messages"][:10]


# ------------------------------------------------------------------------------------- tests
def test_whole_avatar_rigged_in_place_everything_else_kept(avatar_file, stand_in, tmp_path):
    path, world, labels = avatar_file
    method = autorig.RigAnyFaceNetwork()
    result = autorig.auto_rig_avatar(path, tmp_path / "out.glb", method=method)
    assert result.head_node == HEAD_NODE
    assert result.head_meshes == ("HeadSkin", "EyeLeft", "EyeRight")  # not the body, not hair
    [(given, faces, options)] = stand_in
    assert options["method"] is method
    # the face, in cm at bind: the head skin minus its neck ring (weighted to the neck), eyes
    skin = world[labels == 0]
    on_neck = skin[:, 1] < skin[:, 1].min() + 0.03
    face_cm = np.concatenate([skin[~on_neck], world[labels == 1], world[labels == 2]]) * 100
    assert len(given) <= len(face_cm)
    np.testing.assert_allclose(np.sort(given, axis=0)[[0, -1]],
                               np.sort(face_cm, axis=0)[[0, -1]], atol=1e-3)  # fmt: skip
    before, after = read_gltf_avatar(path), read_gltf_avatar(tmp_path / "out.glb")
    # byte for byte: the old buffer is a prefix, the JSON differs only where targets go
    assert after.blob[: len(before.blob)] == before.blob
    old, new = before.document, after.document
    for key in set(old) | set(new):
        if key not in ("meshes", "buffers", "bufferViews", "accessors"):
            assert old.get(key) == new.get(key), key
    assert new["bufferViews"][: len(old["bufferViews"])] == old["bufferViews"]
    assert new["accessors"][: len(old["accessors"])] == old["accessors"]
    for m, (a, b) in enumerate(zip(old["meshes"], new["meshes"], strict=True)):
        if a["name"] in ("Body", "Hair"):
            assert a == b
            continue
        assert b["extras"]["targetNames"] == list(NAMES) and b["weights"] == [0.0] * 3
        assert [p["attributes"] for p in a["primitives"]] == [
            p["attributes"] for p in b["primitives"]
        ]
        # each target, taken to the world and to cm, is the closed form at the face's vertices
        layout = {v.mesh: v for v in mesh_vertices(before)}[m]
        local = _targets(after, m)
        world_cm = np.einsum("vij,kvj->kvi", layout.to_world, local) * 100
        expected = _closed_form(given.astype(np.float64))
        distance, nearest = cKDTree(given).query(layout.world * 100)
        moving = distance < 1e-3
        assert moving.any()
        got = world_cm[:, moving]
        want = expected[:, nearest[moving]]
        np.testing.assert_allclose(got, want, atol=1e-4)
        np.testing.assert_array_equal(world_cm[:, ~moving], 0.0)
    _validate(tmp_path / "out.glb")


def test_only_the_default_scene_is_rigged_and_every_scene_kept(tmp_path, data_dir, stand_in):
    """A file of two scenes: the head and face meshes of the default scene are rigged (a second
    scene's head is not "another head", its meshes get no targets) and the scenes stay."""
    build_avatar(tmp_path / "two.glb", data_dir, extra_head=True)
    avatar = read_gltf_avatar(tmp_path / "two.glb")
    document = avatar.document
    spare = next(i for i, n in enumerate(document["nodes"]) if n["name"] == "Spare Head")
    body = next(i for i, m in enumerate(document["meshes"]) if m["name"] == "Body")
    document["nodes"][spare]["mesh"] = len(document["meshes"])  # a face-sized box of its own
    document["meshes"].append(copy.deepcopy(document["meshes"][body]) | {"name": "SpareFace"})
    document["scenes"][0]["nodes"].remove(spare)
    document["scenes"].append({"name": "spare", "nodes": [spare]})
    write_gltf_avatar(avatar, tmp_path / "scenes.glb")
    said = []
    result = autorig.auto_rig_avatar(tmp_path / "scenes.glb", tmp_path / "out.glb",
                                     progress=said.append)  # fmt: skip
    assert result.head_node == HEAD_NODE
    assert result.head_meshes == ("HeadSkin", "EyeLeft", "EyeRight")
    assert any("2 scenes" in line and "default scene (scene 0)" in line for line in said)
    out = read_gltf_avatar(tmp_path / "out.glb").document
    assert out["scenes"] == document["scenes"]
    assert "targets" not in out["meshes"][-1]["primitives"][0]
    # the spare scene made the default: its head is the one found, and it has no face
    document["scene"] = 1
    write_gltf_avatar(avatar, tmp_path / "spare.glb")
    assert find_head_node(read_gltf_avatar(tmp_path / "spare.glb")) == spare


def test_a_face_rig_failing_a_hard_check_is_flagged_or_with_strict_not_written(
    avatar_file, stand_in, tmp_path, monkeypatch
):
    """The rigger's checks run on the face rig before anything is written: a failed hard check
    is in ``AvatarRig.checks``; with ``strict`` it is a ValueError naming the check, and an
    existing output is left as it was."""
    path, _, _ = avatar_file
    seen = []

    def failing(result):
        seen.append(result.rig)
        return _report(False)

    monkeypatch.setattr("canrig_jax.autorig._avatar.check_auto_rig", failing)
    written = autorig.auto_rig_avatar(path, tmp_path / "out.glb")
    assert written.checks is not None and written.checks.failed == ("blink_closes",)
    assert seen[0].names == NAMES  # the face rig itself was checked
    out = tmp_path / "strict.glb"
    out.write_bytes(b"before")
    with pytest.raises(ValueError, match=r"avatar: .*blink_closes \(0.4, limit 0.1\).*not written"):
        autorig.auto_rig_avatar(path, out, strict=True)
    assert out.read_bytes() == b"before"
    assert autorig.auto_rig_avatar(path, tmp_path / "unchecked.glb", check=False).checks is None


def test_targets_of_a_name_are_refused_then_replaced(avatar_file, stand_in, tmp_path):
    path, _, _ = avatar_file
    once = tmp_path / "once.glb"
    autorig.auto_rig_avatar(path, once)
    twice = read_gltf_avatar(once)
    m = next(i for i, mesh in enumerate(twice.document["meshes"]) if mesh["name"] == "HeadSkin")
    n = len(twice.document["meshes"][m]["primitives"][0]["targets"])
    assert n == 3
    deltas = {m: np.full((3, _targets(twice, m).shape[1], 3), 0.01)}
    with pytest.raises(ValueError, match="replace"):
        add_morph_targets(twice, deltas, NAMES)
    replaced = add_morph_targets(twice, deltas, NAMES, replace=True)
    assert replaced.document["meshes"][m]["extras"]["targetNames"] == list(NAMES)
    np.testing.assert_allclose(_targets(replaced, m), 0.01, atol=1e-7)
    extended = add_morph_targets(twice, deltas, ("viseme_aa", "viseme_E", "viseme_I"))
    names = extended.document["meshes"][m]["extras"]["targetNames"]
    assert names == [*NAMES, "viseme_aa", "viseme_E", "viseme_I"]
    np.testing.assert_array_equal(_targets(extended, m)[:3], _targets(twice, m))


def test_clear_errors_before_compiled_work_and_out_kept(tmp_path, data_dir, refuse_rig):
    out = tmp_path / "out.glb"
    out.write_bytes(b"an earlier result")
    two = build_avatar(tmp_path / "two.glb", data_dir, extra_head=True) and tmp_path / "two.glb"
    with pytest.raises(ValueError, match="2 unrelated nodes are named like a head"):
        autorig.auto_rig_avatar(two, out)
    build_avatar(tmp_path / "none.glb", data_dir, head_name="Skull")
    with pytest.raises(ValueError, match="no head bone"):
        autorig.auto_rig_avatar(tmp_path / "none.glb", out)
    build_avatar(tmp_path / "big.glb", data_dir, grid=450)  # 202,500 face vertices more
    with pytest.raises(ValueError, match="over the limit of 200000"):
        autorig.auto_rig_avatar(tmp_path / "big.glb", out)
    vrm0 = read_gltf_avatar(tmp_path / "none.glb")
    vrm0.document["extensions"] = {"VRM": {"specVersion": "0.0"}}
    write_gltf_avatar(vrm0, tmp_path / "old.vrm")
    with pytest.raises(ValueError, match="VRM 0.x"):
        autorig.auto_rig_avatar(tmp_path / "old.vrm", out)
    assert out.read_bytes() == b"an earlier result"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["out.glb", "two.glb", "none.glb", "big.glb", "old.vrm"]
    )  # no temporary file left


def test_fbx_scene_becomes_a_valid_gltf_avatar(data_dir, tmp_path):
    path = data_file("rocketbox/Male_Adult_08_facial.fbx", data_dir)
    scene = load_fbx_scene(path)
    written = write_gltf_avatar(avatar_from_fbx(scene), tmp_path / "male.glb")
    avatar = read_gltf_avatar(written)
    document = avatar.document
    assert [n["name"] for n in document["nodes"]] == list(scene.node_names[1:])  # root implicit
    [mesh] = scene.meshes
    [skin] = document["skins"]
    assert [document["nodes"][j]["name"] for j in skin["joints"]] == [
        scene.node_names[b] for b in mesh.skin.bones
    ]
    [vertices] = mesh_vertices(avatar)
    # bind pose through the skin equals the FBX's vertices (cm); weights as stored
    np.testing.assert_allclose(vertices.world * 100, mesh.vertices, atol=2e-3)
    stored = np.zeros((len(mesh.vertices), len(mesh.skin.bones)))
    np.add.at(stored, (np.arange(len(stored))[:, None], mesh.skin.joints), mesh.skin.weights)
    got = np.zeros_like(stored)
    names = [document["nodes"][j]["name"] for j in skin["joints"]]
    column = {n: i for i, n in enumerate(names)}
    joint_names = np.array(document["nodes"], dtype=object)[vertices.joints]
    for v, w, nodes in zip(range(len(got)), vertices.weights, joint_names, strict=True):
        for weight, node in zip(w, nodes, strict=True):
            got[v, column[node["name"]]] += weight
    np.testing.assert_allclose(got, stored / stored.sum(axis=1, keepdims=True), atol=1e-6)
    assert "targets" not in document["meshes"][0]["primitives"][0]  # the artist's not carried
    _validate(written)


@pytest.mark.slow
@pytest.mark.parametrize("name", ROCKETBOX)
def test_rocketbox_body_through_the_command(name, data_dir, tmp_path, capsys):
    """The issue's target: a whole-body FBX in, a valid GLB with the skeleton, skin and every
    mesh out, 51+ ARKit targets on the face mesh (the artist's shapes ignored); and the
    rig's jawOpen opens the jaw as the artist's does (downwards in the lower face)."""
    path = data_file(f"rocketbox/{name}_facial.fbx", data_dir)
    out = tmp_path / "rigged.glb"
    status = run_command(
        ["autorig", str(path), "-o", str(out), "--quiet", "--extras", "visemes,rpm"]
    )
    err = capsys.readouterr().err
    assert status == 0, err
    scene = load_fbx_scene(path)
    avatar = read_gltf_avatar(out)
    document = avatar.document
    assert len(document["nodes"]) == len(scene.node_names) - 1
    assert len(document["skins"][0]["joints"]) == len(scene.meshes[0].skin.bones)
    assert len(document["meshes"]) == len(scene.meshes)
    names = document["meshes"][0]["extras"]["targetNames"]
    assert len(names) >= 51 and "jawOpen" in names and not any("AK_" in n for n in names)
    # the extras, after the ARKit targets, exactly their documented sums of the written ones
    targets = _targets(avatar, 0)
    extras = {n: t for table in EXTRA_SHAPES.values() for n, t in table.items()}
    assert names[-len(extras) :] == list(extras)
    for name, terms in extras.items():
        expected = sum(
            (w * targets[names.index(k)] for k, w in terms.items() if k in names),
            np.zeros(targets.shape[1:]),
        )
        np.testing.assert_allclose(targets[names.index(name)], expected, atol=1e-7, err_msg=name)
    [vertices] = mesh_vertices(avatar)
    np.testing.assert_allclose(vertices.world * 100, scene.meshes[0].vertices, atol=2e-3)
    jaw = _targets(avatar, 0)[names.index("jawOpen")] * 100  # cm, the FBX's frame (y up)
    artist = load_fbx(path)
    theirs = artist.deltas[[i for i, n in enumerate(artist.names) if n.endswith("JawOpen")][0]]
    strong = np.linalg.norm(theirs, axis=1) > 0.5 * np.linalg.norm(theirs, axis=1).max()
    cosine = (jaw[strong] * theirs[strong]).sum() / (
        np.linalg.norm(jaw[strong]) * np.linalg.norm(theirs[strong])
    )
    assert cosine > 0.5, cosine
    assert jaw[strong, 1].mean() < 0  # down
    _validate(out)
    [seen] = _three(out)["meshes"]  # three.js: the face mesh, skinned, its targets by name
    assert seen["skinned"] and seen["targets"] == names
    assert seen["vertices"] == len(scene.meshes[0].vertices)


def test_vrm_output_binds_presets_and_arkit_customs(avatar_file, stand_in, tmp_path, data_dir):
    """``-o OUT.vrm``: VRMC_vrm 1.0 with every preset bound to its ARKit combination and each
    ARKit target a custom expression of its own name, binds pointing at the right targets."""
    from canrig_jax.rig import REQUIRED_BONES, VRM_PRESETS, humanoid_bones

    path, _, _ = avatar_file
    with pytest.raises(ValueError, match="humanoid skeleton"):  # hips, spine... but no arms
        autorig.auto_rig_avatar(path, tmp_path / "no.vrm")
    assert not stand_in  # refused before rigging
    fbx = data_file("rocketbox/Male_Adult_08_facial.fbx", data_dir)
    bones = humanoid_bones(avatar_from_fbx(load_fbx_scene(fbx)).document)
    assert set(REQUIRED_BONES) <= set(bones)
    result = autorig.auto_rig_avatar(fbx, tmp_path / "male.vrm", extras=())
    avatar = read_gltf_avatar(result.out)
    document = avatar.document
    vrm = document["extensions"]["VRMC_vrm"]
    assert vrm["specVersion"] == "1.0" and "VRMC_vrm" in document["extensionsUsed"]
    assert document["nodes"][vrm["humanoid"]["humanBones"]["head"]["node"]]["name"] == (
        "Bip01 Head"
    )
    preset, custom = vrm["expressions"]["preset"], vrm["expressions"]["custom"]
    assert set(preset) == set(VRM_PRESETS) and not set(custom) & set(preset)
    names = document["meshes"][0]["extras"]["targetNames"]
    for expression, terms in [*VRM_PRESETS.items(), *((n, {n: 1.0}) for n in custom)]:
        binds = (preset.get(expression) or custom[expression])["morphTargetBinds"]
        got = {names[b["index"]]: b["weight"] for b in binds}
        assert got == {k: w for k, w in terms.items() if k in names}, expression
        assert all(document["nodes"][b["node"]]["mesh"] == 0 for b in binds)
    assert set(custom) == {n for n in names if n in NAMES}
    _validate_as_glb(result.out, tmp_path)
    seen = _three(result.out)["vrm"]  # three-vrm: the expressions an app can set
    assert seen["metaVersion"] == "1" and seen["head"].replace("_", " ") == "Bip01 Head"
    assert set(seen["expressions"]) == set(preset) | set(custom)
    assert seen["expressions"]["aa"] == 1 and seen["expressions"]["neutral"] == 0
    assert seen["jawOpenAfterAa"] == pytest.approx(VRM_PRESETS["aa"]["jawOpen"])


def _validate_as_glb(path, tmp_path):
    copy = tmp_path / (path.stem + "_copy.glb")
    copy.write_bytes(path.read_bytes())
    _validate(copy)


@pytest.mark.slow
def test_whole_avatar_with_the_real_rig(avatar_file, tmp_path):
    """The built avatar through the real ``auto_rig`` (the default method): the head skin and
    both eyes get the same named targets, the rest byte for byte, valid, loaded in three.js."""
    path, _, _ = avatar_file
    result = autorig.auto_rig_avatar(path, tmp_path / "real.glb", extras=("visemes", "rpm"))
    assert result.head_meshes == ("HeadSkin", "EyeLeft", "EyeRight")
    before, after = read_gltf_avatar(path), read_gltf_avatar(result.out)
    assert after.blob[: len(before.blob)] == before.blob
    names = [m["extras"]["targetNames"] for m in after.document["meshes"] if "extras" in m]
    assert len(names) == 3 and names[0] == names[1] == names[2] and len(names[0]) >= 51 + 20
    _validate(result.out)
    seen = {m["name"]: m["targets"] for m in _three(result.out)["meshes"]}
    assert seen["HeadSkinMesh"] == seen["EyeLeftNode"] == names[0]  # three.js: node names


def test_viewer_renders_the_whole_avatar_and_its_face_moves(avatar_file, stand_in, tmp_path):
    """``canrig view --screenshot`` (headless Chromium, the viewer's three.js) draws the rigged
    avatar; holding jawOpen at 1 changes pixels only in the head's part of the frame."""
    import matplotlib.image

    from canrig_jax.viewer import find_chromium

    if find_chromium() is None:
        pytest.skip("no headless Chromium: apt-get install chromium-headless-shell")
    path, _, _ = avatar_file
    out = autorig.auto_rig_avatar(path, tmp_path / "out.glb").out
    shots = []
    for morph in ([], ["--morph", "jawOpen=1"]):
        png = tmp_path / f"shot{len(shots)}.png"
        argv = ["view", str(out), "--screenshot", str(png), "--size", "480x640", *morph]
        assert run_command(argv) == 0
        shots.append(matplotlib.image.imread(png)[..., :3])
    rest, jaw = shots
    canvas = rest[:, : int(rest.shape[1] * 0.7)]  # the 3-D view (the panel is on the right)
    drawn = np.abs(canvas - canvas[0, 0]).sum(axis=-1) > 0.05
    assert drawn.mean() > 0.01  # the avatar is drawn
    changed = np.abs(jaw - rest).sum(axis=-1)[:, : canvas.shape[1]] > 0.05
    assert changed.any()
    rows = np.flatnonzero(changed.any(axis=1))
    body_rows = np.flatnonzero(drawn.any(axis=1))
    top, bottom = body_rows.min(), body_rows.max()
    assert rows.max() < top + 0.35 * (bottom - top)  # the head, not the body, moved
    # --face frames what the targets move: the head fills the view, jawOpen changes far more
    framed = []
    for morph in ([], ["--morph", "jawOpen=1"]):
        png = tmp_path / f"face{len(framed)}.png"
        argv = ["view", str(out), "--screenshot", str(png), "--size", "480x640", "--face", *morph]
        assert run_command(argv) == 0
        framed.append(matplotlib.image.imread(png)[..., :3])
    moved = np.abs(framed[1] - framed[0]).sum(axis=-1)[:, : canvas.shape[1]] > 0.05
    assert moved.mean() > 3 * changed.mean(), (moved.mean(), changed.mean())


@pytest.mark.parametrize("name", ROCKETBOX)
def test_a_standing_body_without_a_skeleton_gives_its_head_by_geometry(
    name, data_dir, tmp_path, stand_in
):
    """A Rocketbox body written as a plain GLB (its bind pose, no skin, no bones): the head
    found by geometry is the head bone's (most of its vertices, almost nothing else), and
    ``auto_rig_avatar`` rigs just those vertices."""
    import trimesh

    from canrig_jax.autorig._avatar import _face_selection, standing_body

    skinned = avatar_from_fbx(load_fbx_scene(data_file(f"rocketbox/{name}_facial.fbx", data_dir)))
    [layout] = mesh_vertices(skinned)
    path = tmp_path / "static.glb"
    trimesh.Trimesh(layout.world, layout.faces, process=False).export(path)
    bare = read_gltf_avatar(path)
    assert not bare.document.get("skins") and standing_body(bare)
    [(_, bone)] = _face_selection(skinned, find_head_node(skinned))
    [(found, geometric)] = _face_selection(bare, None)
    np.testing.assert_allclose(found.world, layout.world, atol=1e-6)  # same vertices, order
    assert (bone & geometric).sum() >= 0.7 * bone.sum()
    assert (geometric & ~bone).sum() <= 0.1 * geometric.sum()
    result = autorig.auto_rig_avatar(path, tmp_path / "out.glb")
    [(given, _, _)] = stand_in
    assert len(given) == geometric.sum() and result.head_node is None
    # canrig autorig takes the plain body as an avatar (not "182 cm tall: crop it")
    assert run_command(["autorig", str(path), "-o", str(tmp_path / "cli.glb"), "--quiet"]) == 0
    assert len(stand_in) == 2 and len(stand_in[1][0]) == geometric.sum()
