"""glTF 2.0 export of a blendshape rig: one mesh, one morph target per blendshape.

glTF morph targets are linear (position = base + sum_i w_i target_i), so the rig's deltas map
one to one onto named targets (``mesh.extras.targetNames``, the convention Blender and
three.js read). A corrective term has no linear equivalent: it is exported as one more
target, named "a+b+..." after its expressions, and ``mesh.extras.correctives`` records its
drivers; a player sets its weight to the product of the drivers' weights (Racković eq. (5)).

``load_gltf_rig`` re-reads the file: the base mesh through ``trimesh`` (an independent glTF
reader), the morph targets from the file's accessors (trimesh does not parse morph targets).
"""

import json
import os
import struct
from pathlib import Path

import numpy as np

from .._io import CorruptFileError, atomic_path, check_output_path
from ._blendshape import BlendshapeRig, Corrective

_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Buffer:
    """One glTF binary buffer with its buffer views and accessors, built up in order."""

    def __init__(self):
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target=None, bounds=False) -> int:
        """Append ``array`` (rows of ``kind``: "SCALAR", "VEC3", "VEC4"); its accessor index."""
        offset = len(self.blob)
        self.blob.extend(np.ascontiguousarray(array).tobytes())
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": offset, "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        accessor = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": int(array.size) if kind == "SCALAR" else int(array.shape[0]),
            "type": kind,
        }
        if bounds:
            rows = array.reshape(accessor["count"], -1)
            accessor["min"] = rows.min(axis=0).tolist()
            accessor["max"] = rows.max(axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _check_rig(rig: BlendshapeRig, path) -> None:
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    check_output_path(path)
    if rig.faces is None:
        raise ValueError("rig: glTF export needs a rig with faces")


def _rig_document(rig: BlendshapeRig) -> tuple[dict, _Buffer, list[list[int]]]:
    """The glTF document and buffer of ``rig`` (one node, one mesh, one morph target per
    blendshape and per corrective term) and the driver indices of each corrective target."""
    n = rig.n_vertices
    neutral = np.asarray(rig.neutral, np.float32)
    faces = np.asarray(rig.faces, np.uint32)
    targets = [np.asarray(d, np.float32) for d in np.asarray(rig.deltas)]
    names = list(rig.names) or [f"shape{i}" for i in range(len(targets))]
    correctives, drivers_of = [], []
    for table in rig.correctives:
        dense = table.to_dense(n)
        for row, indices in enumerate(np.asarray(table.indices)):
            drivers = [names[i] for i in indices]
            correctives.append({"target": len(targets), "drivers": drivers})
            drivers_of.append([int(i) for i in indices])
            targets.append(dense[row])
            names.append("+".join(drivers))

    buffer = _Buffer()
    position = buffer.add(neutral, _FLOAT, "VEC3", _ARRAY_BUFFER, True)
    indices = buffer.add(faces.reshape(-1), _UINT32, "SCALAR", _ELEMENT_ARRAY_BUFFER)
    target_accessors = [
        {"POSITION": buffer.add(t, _FLOAT, "VEC3", _ARRAY_BUFFER, True)} for t in targets
    ]
    primitive = {"attributes": {"POSITION": position}, "indices": indices, "mode": 4}
    # glTF allows no empty list of targets or weights: a rig without blendshapes has neither
    morphs = {"weights": [0.0] * len(targets)} if targets else {}
    if targets:
        primitive["targets"] = target_accessors
    document = {
        "asset": {"version": "2.0", "generator": "canrig_jax"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "rig"}],
        "meshes": [
            {
                "name": "rig",
                "primitives": [primitive],
                **morphs,
                "extras": {
                    "targetNames": names,
                    "blendshapes": len(rig.names),
                    "correctives": correctives,
                    "units": rig.units,
                },
            }
        ],
    }
    return document, buffer, drivers_of


def _write_glb(path, document: dict, buffer: _Buffer) -> Path:
    """Write ``document`` and ``buffer`` as one .glb file, atomically."""
    document = {
        **document,
        "buffers": [{"byteLength": len(buffer.blob)}],
        "bufferViews": buffer.views,
        "accessors": buffer.accessors,
    }
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    chunks += struct.pack("<II", len(buffer.blob), 0x004E4942) + bytes(buffer.blob)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)))
        f.write(chunks)
    return Path(path)


def export_gltf(rig: BlendshapeRig, path: str | os.PathLike) -> Path:
    """Write ``rig`` as a binary glTF 2.0 file (.glb), atomically. Needs faces; a rig with
    no blendshapes is written as a plain mesh (glTF has no empty morph-target list) and
    ``load_gltf_rig`` reads it back with none.

    Positions are in the rig's units (recorded in ``mesh.extras.units``; glTF viewers assume
    metres). A ``path`` that cannot be written (a folder, under a file, no permission)
    raises an OSError naming ``path`` before anything is written."""
    _check_rig(rig, path)
    document, buffer, _ = _rig_document(rig)
    return _write_glb(path, document, buffer)


def _read_glb(path) -> tuple[dict, bytes]:
    data = Path(path).read_bytes()
    if len(data) < 12:
        raise CorruptFileError(f"path: corrupt glTF file {path} (truncated, {len(data)} bytes)")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != 0x46546C67 or version != 2:
        raise ValueError(f"path: {path} is not a binary glTF 2.0 file")
    if length != len(data):
        raise CorruptFileError(
            f"path: corrupt glTF file {path} (header says {length} bytes, the file has "
            f"{len(data)}: truncated or damaged)"
        )
    try:
        json_length, _ = struct.unpack_from("<II", data, 12)
        document = json.loads(data[20 : 20 + json_length])
        bin_start = 20 + json_length
        bin_length, _ = struct.unpack_from("<II", data, bin_start)
    except (struct.error, ValueError) as error:
        raise CorruptFileError(f"path: corrupt glTF file {path} ({error})") from error
    return document, data[bin_start + 8 : bin_start + 8 + bin_length]


def _accessor(document: dict, blob: bytes, index: int) -> np.ndarray:
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    dtype = {_FLOAT: np.float32, _UINT32: np.uint32}[accessor["componentType"]]
    width = {"VEC3": 3, "SCALAR": 1}[accessor["type"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    values = np.frombuffer(blob, dtype, accessor["count"] * width, start)
    return values.reshape(accessor["count"], width) if width > 1 else values


def load_gltf_rig(path: str | os.PathLike) -> BlendshapeRig:
    """The ``BlendshapeRig`` of a file written by ``export_gltf`` (base mesh via trimesh).

    A missing file raises FileNotFoundError, a damaged one ``CorruptFileError`` (a
    ValueError), both naming ``path``."""
    import trimesh

    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"path: glTF file {path} not found")
    document, blob = _read_glb(path)  # checks the container before trimesh reads it
    try:
        loaded = trimesh.load(os.fspath(path), force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds on a damaged file
        raise CorruptFileError(f"path: corrupt glTF file {path} ({error})") from error
    if not isinstance(loaded, trimesh.Trimesh):
        raise CorruptFileError(f"path: glTF file {path} holds no triangle mesh")
    mesh = document["meshes"][0]
    extras = mesh.get("extras", {})
    primitive = mesh["primitives"][0]
    targets = [_accessor(document, blob, t["POSITION"]) for t in primitive.get("targets", [])]
    vertices = np.asarray(loaded.vertices, np.float32)
    targets = np.stack(targets) if targets else np.zeros((0, *vertices.shape), np.float32)
    names = extras.get("targetNames", [f"shape{i}" for i in range(len(targets))])
    k = int(extras.get("blendshapes", len(targets)))
    by_order: dict[int, tuple[list, list]] = {}
    lookup = {name: i for i, name in enumerate(names[:k])}
    for corrective in extras.get("correctives", []):
        drivers = [lookup[d] for d in corrective["drivers"]]
        rows, dense = by_order.setdefault(len(drivers), ([], []))
        rows.append(drivers)
        dense.append(targets[corrective["target"]])
    correctives = tuple(
        Corrective.from_dense(np.asarray(rows), np.stack(dense))
        for _, (rows, dense) in sorted(by_order.items())
    )
    return BlendshapeRig(
        vertices,
        targets[:k],
        correctives,
        tuple(names[:k]),
        np.asarray(loaded.faces, np.int32),
        units=extras.get("units", "cm"),
    )
