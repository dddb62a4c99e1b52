"""Whole avatars in glTF: read one, add morph targets to some of its meshes in place, and build
one from an FBX scene.

An avatar is a glTF document and its binary buffer (``GltfAvatar``). ``add_morph_targets``
changes nothing but what it adds: the new targets' bytes are appended after the buffer's
(every earlier byte kept, so every accessor, image and animation keeps its offsets), new
buffer views and accessors come after the old ones, and of the JSON only the rigged meshes'
``primitives[*].targets``, ``weights`` and ``extras.targetNames`` and the buffer's length
change. A primitive of a rigged mesh that holds none of the rigged vertices gets all-zero
targets (accessors without a buffer view, which glTF defines as zeros).

``avatar_from_fbx`` writes an FBX scene as such a document: the node tree (TRS, metres, y
up), every mesh (positions, normals, triangles) and its skin (joints, weights renormalised to
sum 1, inverse bind matrices). Not carried: materials, textures, UVs, blend shapes,
animations, cameras and lights.
"""

import dataclasses
import json
import os
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Float, Float64, Int

from .._io import CorruptFileError, atomic_path, check_output_path
from ..data import FbxScene
from ._gltf import _read_glb

_COMPONENTS = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORMALISED_MAX = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_FLOAT, _UINT16, _UINT32, _TRIANGLES = 5126, 5123, 5125, 4
METRES_TO_CM = 100.0


@dataclasses.dataclass
class GltfAvatar:
    """A glTF 2.0 document (the parsed JSON) and its one binary buffer (a GLB's BIN chunk)."""

    document: dict
    blob: bytes
    path: Path | None = None


def read_gltf_avatar(path: str | os.PathLike) -> GltfAvatar:
    """The document and buffer of a binary glTF (``.glb``, ``.vrm``). ValueError naming
    ``path`` for a file that is not one, or that keeps buffers in other files."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: glTF file {path} not found")
    if path.suffix.lower() == ".gltf":
        raise ValueError(
            f"path: {path} is a text .gltf; save it as a binary .glb (one file) and pass that"
        )
    document, blob = _read_glb(path)
    buffers = document.get("buffers", [])
    if len(buffers) > 1 or any("uri" in b for b in buffers):
        raise ValueError(
            f"path: {path} keeps buffers in other files ({len(buffers)} buffers); pass a .glb "
            "that holds its one buffer"
        )
    return GltfAvatar(document, bytes(blob), path)


def accessor_array(avatar: GltfAvatar, index: int) -> Float64[np.ndarray, "N W"]:
    """(count, width) float64 values of accessor ``index`` (strides, sparse substitution and
    normalised integers applied)."""
    document = avatar.document
    accessor = document["accessors"][index]
    width = _WIDTHS[accessor["type"]]
    count = int(accessor["count"])
    dtype = np.dtype(_COMPONENTS[accessor["componentType"]])
    if "bufferView" in accessor:
        view = document["bufferViews"][accessor["bufferView"]]
        start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
        stride = view.get("byteStride", width * dtype.itemsize)
        if count and start + stride * (count - 1) + width * dtype.itemsize > len(avatar.blob):
            raise CorruptFileError(f"accessor {index} reads past the end of the buffer")
        rows = np.ndarray(
            (count, width), dtype, avatar.blob, start, (stride, dtype.itemsize)
        ).astype(np.float64)
    else:
        rows = np.zeros((count, width))
    sparse = accessor.get("sparse")
    if sparse:
        n = int(sparse["count"])
        at = sparse["indices"]
        at_view = document["bufferViews"][at["bufferView"]]
        at_dtype = _COMPONENTS[at["componentType"]]
        at_start = at_view.get("byteOffset", 0) + at.get("byteOffset", 0)
        where = np.frombuffer(avatar.blob, at_dtype, n, at_start).astype(np.int64)
        values = sparse["values"]
        v_view = document["bufferViews"][values["bufferView"]]
        v_start = v_view.get("byteOffset", 0) + values.get("byteOffset", 0)
        rows[where] = np.frombuffer(avatar.blob, dtype, n * width, v_start).reshape(n, width)
    if accessor.get("normalized") and accessor["componentType"] in _NORMALISED_MAX:
        rows = np.maximum(rows / _NORMALISED_MAX[accessor["componentType"]], -1.0)
    return rows


def _trs_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    matrix = np.eye(4)
    matrix[:3, :3] = rotation * np.asarray(node.get("scale", (1.0, 1.0, 1.0)))[None, :]
    matrix[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return matrix


def node_parents(document: dict) -> Int[np.ndarray, " N"]:
    """(N,) the parent of each node, -1 for a root."""
    parents = np.full(len(document.get("nodes", [])), -1, np.int64)
    for i, node in enumerate(document.get("nodes", [])):
        for child in node.get("children", []):
            parents[child] = i
    return parents


def node_world_matrices(document: dict) -> Float64[np.ndarray, "N 4 4"]:
    """(N, 4, 4) each node's world matrix in the file's rest pose (its TRS / matrix)."""
    nodes = document.get("nodes", [])
    parents = node_parents(document)
    world = np.zeros((len(nodes), 4, 4))
    done = np.zeros(len(nodes), bool)

    def visit(i: int) -> np.ndarray:
        if not done[i]:
            local = _trs_matrix(nodes[i])
            world[i] = local if parents[i] < 0 else visit(int(parents[i])) @ local
            done[i] = True
        return world[i]

    for i in range(len(nodes)):
        visit(i)
    return world


def node_descendants(document: dict, root: int) -> set[int]:
    """``root`` and every node below it."""
    nodes, out, stack = document.get("nodes", []), set(), [root]
    while stack:
        i = stack.pop()
        if i not in out:
            out.add(i)
            stack.extend(nodes[i].get("children", []))
    return out


def scene_nodes(document: dict) -> set[int]:
    """The nodes of the document's default scene (``scene``, else the first of ``scenes``)
    and every node below them; every node when the document has no scene."""
    scenes = document.get("scenes", [])
    if not scenes:
        return set(range(len(document.get("nodes", []))))
    roots = scenes[int(document.get("scene", 0))].get("nodes", [])
    return set().union(*(node_descendants(document, r) for r in roots))


@dataclasses.dataclass(frozen=True)
class MeshVertices:
    """One glTF mesh's vertices (each POSITION accessor once) in the world at bind time.

    Attributes:
        mesh: the mesh index; node: the (first) node that instances it.
        accessors: the POSITION accessors, in primitive order, each once.
        offsets: the first row of each accessor in ``world``.
        world: (V, 3) float64 positions in the world (the file's units).
        to_world: (V, 3, 3) the linear map of each vertex from the mesh's frame to the world
            (its skin matrix, or the node's world matrix).
        faces: (F, 3) triangles into ``world`` (triangle-list primitives only).
        joints, weights: (V, M) the skin's joints (node indices) and weights; None unskinned.
    """

    mesh: int
    node: int
    accessors: tuple[int, ...]
    offsets: tuple[int, ...]
    world: Float64[np.ndarray, "V 3"]
    to_world: Float64[np.ndarray, "V 3 3"]
    faces: Int[np.ndarray, "F 3"]
    joints: Int[np.ndarray, "V M"] | None
    weights: Float64[np.ndarray, "V M"] | None


def _skin_of(avatar: GltfAvatar, node: dict, primitive: dict, world_nodes: np.ndarray):
    """(V, 4, 4) skin matrices, (V, M) joint nodes and weights of a skinned primitive."""
    document = avatar.document
    skin = document["skins"][node["skin"]]
    joint_nodes = np.asarray(skin["joints"], np.int64)
    if "inverseBindMatrices" in skin:
        ibm = accessor_array(avatar, skin["inverseBindMatrices"]).reshape(-1, 4, 4)
        ibm = np.transpose(ibm, (0, 2, 1))  # column-major
    else:
        ibm = np.broadcast_to(np.eye(4), (len(joint_nodes), 4, 4))
    joint_matrices = world_nodes[joint_nodes] @ ibm
    attributes = primitive["attributes"]
    sets = sorted(k for k in attributes if k.startswith("JOINTS_"))
    joints = np.concatenate([accessor_array(avatar, attributes[k]) for k in sets], axis=1)
    weights = np.concatenate(
        [accessor_array(avatar, attributes["WEIGHTS_" + k[7:]]) for k in sets], axis=1
    )
    joints = joints.astype(np.int64)
    total = np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    matrices = np.einsum("vm,vmij->vij", weights / total, joint_matrices[joints])
    return matrices, joint_nodes[joints], weights


def _pad(columns: np.ndarray, width: int) -> np.ndarray:
    return np.pad(columns, ((0, 0), (0, width - columns.shape[1])))


def mesh_vertices(avatar: GltfAvatar) -> list[MeshVertices]:
    """Every mesh the default scene instances (``scene_nodes``), its vertices in the world at
    bind time (``MeshVertices``)."""
    document = avatar.document
    world_nodes = node_world_matrices(document)
    in_scene = scene_nodes(document)
    first_node: dict[int, int] = {}
    for i, node in enumerate(document.get("nodes", [])):
        if "mesh" in node and i in in_scene:
            first_node.setdefault(node["mesh"], i)
    out = []
    for m, n in sorted(first_node.items()):
        node = document["nodes"][n]
        accessors, offsets, worlds, linears, faces = [], [], [], [], []
        joints, weights, total = [], [], 0
        for primitive in document["meshes"][m]["primitives"]:
            a = primitive["attributes"]["POSITION"]
            if a in accessors:
                start = offsets[accessors.index(a)]
            else:
                local = accessor_array(avatar, a)
                if "skin" in node and "JOINTS_0" in primitive["attributes"]:
                    matrices, j, w = _skin_of(avatar, node, primitive, world_nodes)
                    joints.append(j)
                    weights.append(w)
                else:
                    matrices = np.broadcast_to(world_nodes[n], (len(local), 4, 4))
                worlds.append(np.einsum("vij,vj->vi", matrices[:, :3, :3], local))
                worlds[-1] += matrices[:, :3, 3]
                linears.append(np.array(matrices[:, :3, :3]))
                accessors.append(a)
                offsets.append(total)
                start, total = total, total + len(local)
            if primitive.get("mode", _TRIANGLES) == _TRIANGLES:
                count = document["accessors"][a]["count"]
                if "indices" in primitive:
                    index = accessor_array(avatar, primitive["indices"]).astype(np.int64)
                    index = index.reshape(-1)
                else:
                    index = np.arange(count)
                faces.append(index[: len(index) // 3 * 3].reshape(-1, 3) + start)
        width = max((j.shape[1] for j in joints), default=0)
        skinned = len(joints) == len(accessors) and joints
        out.append(
            MeshVertices(
                mesh=m,
                node=n,
                accessors=tuple(accessors),
                offsets=tuple(offsets),
                world=np.concatenate(worlds),
                to_world=np.concatenate(linears),
                faces=np.concatenate(faces) if faces else np.zeros((0, 3), np.int64),
                joints=np.concatenate([_pad(j, width) for j in joints]) if skinned else None,
                weights=np.concatenate([_pad(w, width) for w in weights]) if skinned else None,
            )
        )
    return out


def target_names(document: dict, mesh: int) -> list[str]:
    """The names of a mesh's morph targets (``extras.targetNames``, else ``target{i}``)."""
    entry = document["meshes"][mesh]
    count = len(entry["primitives"][0].get("targets", []))
    names = list(entry.get("extras", {}).get("targetNames", []))[:count]
    return names + [f"target{i}" for i in range(len(names), count)]


class _Appender:
    """New bytes, buffer views and accessors after an avatar's own."""

    def __init__(self, avatar: GltfAvatar):
        self.document = json.loads(json.dumps(avatar.document))  # a deep copy
        self.blob = bytearray(avatar.blob)
        self.document.setdefault("bufferViews", [])
        self.document.setdefault("accessors", [])
        if not self.document.get("buffers"):
            self.document["buffers"] = [{"byteLength": 0}]

    def add(self, array, component: int, kind: str, target=None, bounds=False) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        array = np.ascontiguousarray(array)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": array.nbytes}
        self.blob.extend(array.tobytes())
        if target is not None:
            view["target"] = target
        self.document["bufferViews"].append(view)
        return self.accessor(array, component, kind, len(self.document["bufferViews"]) - 1, bounds)

    def accessor(self, array, component, kind, view, bounds=False) -> int:
        rows = array.reshape(len(array), -1)
        accessor = {"componentType": component, "count": int(len(array)), "type": kind}
        if view is not None:
            accessor["bufferView"] = view
        if bounds:
            accessor["min"] = rows.min(axis=0).astype(float).tolist()
            accessor["max"] = rows.max(axis=0).astype(float).tolist()
        self.document["accessors"].append(accessor)
        return len(self.document["accessors"]) - 1

    def zeros(self, count: int) -> int:
        """A VEC3 float accessor of ``count`` zeros (no buffer view: glTF's zeros)."""
        return self.accessor(np.zeros((count, 3), np.float32), _FLOAT, "VEC3", None, True)

    def finish(self, path) -> GltfAvatar:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.document["buffers"][0]["byteLength"] = len(self.blob)
        return GltfAvatar(self.document, bytes(self.blob), path)


def add_morph_targets(
    avatar: GltfAvatar,
    deltas: Mapping[int, Float[np.ndarray, "K V 3"]],
    names: Sequence[str],
    *,
    replace: bool = False,
    extras: Mapping | None = None,
) -> GltfAvatar:
    """``avatar`` with K morph targets ``names`` added to meshes, in place (module docstring).

    Args:
        avatar: the avatar.
        deltas: {mesh index: (K, V, 3) offsets in the mesh's own frame and units}, V the
            mesh's vertices as ``mesh_vertices`` orders them (each POSITION accessor once, in
            primitive order).
        names: the K target names (written to ``extras.targetNames``).
        replace: a name the mesh already has replaces that target (else a ValueError).
        extras: more entries for each rigged mesh's ``extras``.
    """
    names = list(names)
    layout = {v.mesh: v for v in mesh_vertices(avatar)}
    for m, d in deltas.items():
        if m not in layout or d.shape != (len(names), len(layout[m].world), 3):
            raise ValueError(f"deltas: mesh {m} needs ({len(names)}, V, 3) offsets")
        clash = sorted(set(target_names(avatar.document, m)) & set(names))
        if clash and not replace:
            raise ValueError(
                f"mesh {m} ({avatar.document['meshes'][m].get('name', '')!r}) already has "
                f"morph targets named {clash[:5]}{'...' if len(clash) > 5 else ''}: pass "
                "replace=True (canrig autorig --replace) to replace them"
            )
    out = _Appender(avatar)
    for m, d in sorted(deltas.items()):
        entry, vertices = out.document["meshes"][m], layout[m]
        old = target_names(avatar.document, m)
        slots = [old.index(n) if n in old else None for n in names]
        added = [n for n, s in zip(names, slots, strict=True) if s is None]
        by_accessor: dict[int, list[int]] = {}
        for a, start in zip(vertices.accessors, vertices.offsets, strict=True):
            count = avatar.document["accessors"][a]["count"]
            block = d[:, start : start + count].astype(np.float32)
            by_accessor[a] = [
                out.add(t, _FLOAT, "VEC3", 34962, True) if np.any(t) else out.zeros(count)
                for t in block
            ]
        for primitive in entry["primitives"]:
            made = by_accessor[primitive["attributes"]["POSITION"]]
            targets = primitive.setdefault("targets", [])
            for k, slot in enumerate(slots):
                if slot is None:
                    targets.append({"POSITION": made[k]})
                else:
                    targets[slot] = {"POSITION": made[k]}
        weights = list(entry.get("weights", [0.0] * len(old)))
        entry["weights"] = weights + [0.0] * len(added)
        entry["extras"] = {
            **entry.get("extras", {}),
            "targetNames": old + added,
            **(extras or {}),
        }
    return out.finish(avatar.path)


def write_gltf_avatar(avatar: GltfAvatar, path: str | os.PathLike) -> Path:
    """Write ``avatar`` as one ``.glb`` (or ``.vrm``) file, atomically."""
    check_output_path(path)
    document = avatar.document
    blob = bytearray(avatar.blob)
    while len(blob) % 4:
        blob.append(0)
    if document.get("buffers"):
        document = {**document, "buffers": [{**document["buffers"][0], "byteLength": len(blob)}]}
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if blob:
        chunks += struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)))
        f.write(chunks)
    return Path(path)


def _decompose(matrix: np.ndarray) -> dict:
    """glTF TRS of a 4x4 matrix (rotation and positive scale; a mirror flips the x scale)."""
    from scipy.spatial.transform import Rotation

    linear = matrix[:3, :3]
    scale = np.linalg.norm(linear, axis=0)
    rotation = linear / np.maximum(scale, 1e-12)
    if np.linalg.det(rotation) < 0:
        scale[0], rotation[:, 0] = -scale[0], -rotation[:, 0]
    out = {}
    if np.any(np.abs(matrix[:3, 3]) > 0):
        out["translation"] = matrix[:3, 3].tolist()
    quaternion = Rotation.from_matrix(rotation).as_quat()  # x, y, z, w
    if np.abs(quaternion[:3]).max() > 1e-12:
        out["rotation"] = (quaternion / np.linalg.norm(quaternion)).tolist()
    if np.abs(scale - 1.0).max() > 1e-9:
        out["scale"] = scale.tolist()
    return out


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    normals = np.zeros_like(vertices)
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    face_normals = np.cross(b - a, c - a)
    for i in range(3):
        np.add.at(normals, faces[:, i], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(length > 1e-20, normals / np.maximum(length, 1e-20), [0.0, 1.0, 0.0])
    return normals.astype(np.float32)


def _to_metres(matrices: np.ndarray) -> np.ndarray:
    """(N, 4, 4) matrices in centimetres with their translations in metres."""
    out = matrices.copy()
    out[:, :3, 3] /= METRES_TO_CM
    return out


def avatar_from_fbx(scene: FbxScene) -> GltfAvatar:
    """A ``GltfAvatar`` (metres, y up) of an FBX scene (``data.load_fbx_scene``): its nodes,
    meshes and skins (module docstring). Vertex order is the FBX's control points'."""
    out = _Appender(GltfAvatar({"asset": {"version": "2.0"}}, b""))
    document = out.document
    document["asset"] = {"version": "2.0", "generator": "canrig_jax (from FBX)"}
    world = _to_metres(np.asarray(scene.node_to_world, np.float64))
    parents = np.asarray(scene.node_parents)
    root = [i for i in range(len(parents)) if parents[i] < 0]
    keep = [i for i in range(len(parents)) if i not in root]  # the FBX scene root is implicit
    index = {fbx: i for i, fbx in enumerate(keep)}
    nodes = []
    for i in keep:
        local = world[i] if parents[i] in root else np.linalg.inv(world[parents[i]]) @ world[i]
        name = scene.node_names[i] or f"node{i}"
        nodes.append({"name": name, **_decompose(local)})
    for i in keep:
        if parents[i] not in root:
            nodes[index[parents[i]]].setdefault("children", []).append(index[i])
    document["nodes"], document["meshes"], document["skins"] = nodes, [], []
    for mesh in scene.meshes:
        positions = mesh.vertices.astype(np.float64) / METRES_TO_CM
        attributes = {
            "POSITION": out.add(positions.astype(np.float32), _FLOAT, "VEC3", 34962, True),
            "NORMAL": out.add(_vertex_normals(positions, mesh.triangles), _FLOAT, "VEC3", 34962),
        }
        if mesh.node in index:
            host = index[mesh.node]
        else:
            nodes.append({"name": mesh.name})
            host = len(nodes) - 1
        if mesh.skin is not None:
            _add_skin(out, mesh, index, world, attributes, host)
        elif mesh.node in index:  # vertices are in the world: into the node's frame
            inverse = np.linalg.inv(world[mesh.node])
            local = positions @ inverse[:3, :3].T + inverse[:3, 3]
            attributes["POSITION"] = out.add(local.astype(np.float32), _FLOAT, "VEC3", 34962, True)
        faces = out.add(mesh.triangles.astype(np.uint32).reshape(-1), _UINT32, "SCALAR", 34963)
        primitive = {"attributes": attributes, "indices": faces, "mode": _TRIANGLES}
        document["meshes"].append({"name": mesh.name, "primitives": [primitive]})
        nodes[host]["mesh"] = len(document["meshes"]) - 1
    parents_gltf = {c for n in nodes for c in n.get("children", [])}
    document["scenes"] = [{"nodes": [i for i in range(len(nodes)) if i not in parents_gltf]}]
    document["scene"] = 0
    if not document["skins"]:
        del document["skins"]
    return out.finish(None)


def _add_skin(out: _Appender, mesh, index: dict, world: np.ndarray, attributes, host) -> None:
    skin = mesh.skin
    missing = [int(b) for b in skin.bones if int(b) not in index]
    if missing:
        raise ValueError(f"mesh {mesh.name!r}: skinned to the scene root node ({missing})")
    weights = skin.weights.astype(np.float64)
    joints = skin.joints.astype(np.int64)
    total = weights.sum(axis=1, keepdims=True)
    unweighted = total[:, 0] <= 0
    weights = np.where(unweighted[:, None], 0.0, weights / np.maximum(total, 1e-12))
    weights[unweighted, 0] = 1.0  # a vertex no bone holds follows the first joint
    width = -(-weights.shape[1] // 4) * 4
    joints = np.pad(joints, ((0, 0), (0, width - joints.shape[1])))
    weights = np.pad(weights, ((0, 0), (0, width - weights.shape[1]))).astype(np.float32)
    for s in range(width // 4):
        block = slice(4 * s, 4 * s + 4)
        j = np.where(weights[:, block] > 0, joints[:, block], 0).astype(np.uint16)
        attributes[f"JOINTS_{s}"] = out.add(j, _UINT16, "VEC4", 34962)
        attributes[f"WEIGHTS_{s}"] = out.add(weights[:, block], _FLOAT, "VEC4", 34962)
    inverse = np.linalg.inv(_to_metres(np.asarray(skin.bind_to_world, np.float64)))
    ibm = np.transpose(inverse, (0, 2, 1)).reshape(-1, 16).astype(np.float32)  # column-major
    document = out.document
    joint_nodes = [index[int(b)] for b in skin.bones]
    document["skins"].append(
        {"joints": joint_nodes, "inverseBindMatrices": out.add(ibm, _FLOAT, "MAT4")}
    )
    document["nodes"][host]["skin"] = len(document["skins"]) - 1
