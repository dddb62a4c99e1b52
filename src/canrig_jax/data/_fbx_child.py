"""The child process of ``load_fbx``: reads an FBX file with ufbx, writes its raw arrays.

Run as ``python _fbx_child.py IN.fbx OUT.npz``. Exit status 0 with ``OUT.npz`` written, 3 with
ufbx's error on standard error, 4 when ufbx is not installed. Nothing is converted here
(``_fbx.py`` does that); this process only copies what the file holds.

Why a process of its own: the ufbx 0.0.5 bindings are not memory-safe (element lists hand
out borrowed references, and freeing a scene can touch freed wrappers). Here every element
wrapper gets the reference its list did not give, the garbage collector is off, and the
process ends with ``os._exit`` without freeing the scene, so none of that code runs; a
crash would end only this process, which ``load_fbx`` reports naming the file.
"""

import sys

if __name__ == "__main__":
    del sys.path[0]  # the script's folder: nothing in it may shadow numpy or ufbx

import ctypes  # noqa: E402
import gc  # noqa: E402
import os  # noqa: E402

import numpy as np  # noqa: E402


def _elements(elements) -> list:
    """The items of a ufbx element list, each with the reference the list did not give."""
    out = []
    for i in range(len(elements)):
        item = elements[i]
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(item))
        out.append(item)
    return out


def _matrix(m) -> np.ndarray:
    """(3, 4) affine matrix [A | t] of a ufbx matrix (its columns c0, c1, c2, c3)."""
    return np.array([tuple(m.c0), tuple(m.c1), tuple(m.c2), tuple(m.c3)], np.float64).T


def _mesh_arrays(i: int, mesh) -> dict:
    nodes = _elements(mesh.instances)
    out = {
        f"mesh{i}_name": np.array(mesh.name),
        f"mesh{i}_nodes": np.array([n.name for n in nodes], dtype=str).reshape(-1),
        f"mesh{i}_to_world": (
            _matrix(nodes[0].geometry_to_world) if nodes else np.eye(3, 4, dtype=np.float64)
        ),
        f"mesh{i}_vertices": np.array(mesh.vertices, np.float64).reshape(-1, 3),
        f"mesh{i}_corners": np.array(mesh.vertex_indices, np.int64).reshape(-1),
        f"mesh{i}_faces": np.array(mesh.faces, np.int64).reshape(-1, 2),
        f"mesh{i}_node": np.array(int(nodes[0].typed_id) if nodes else -1),
    }
    out.update(_skin_arrays(i, mesh))
    names, deformers, counts, index, offsets, weights = [], [], [], [], [], []
    for deformer in _elements(mesh.blend_deformers):
        for channel in _elements(deformer.channels):
            names.append(channel.name)
            deformers.append(deformer.name)
            shape = channel.target_shape  # the full-weight shape; in-betweens are not read
            if shape is None:
                counts.append(0)
                continue
            k = np.array(shape.offset_vertices, np.int64).reshape(-1)
            d = np.array(shape.position_offsets, np.float64).reshape(-1, 3)
            w = np.array(shape.offset_weights, np.float64).reshape(-1)
            counts.append(len(k))
            index.append(k)
            offsets.append(d)
            weights.append(w if w.size == len(k) else np.ones(len(k)))
    out[f"mesh{i}_shape_names"] = np.array(names, dtype=str).reshape(-1)
    out[f"mesh{i}_shape_deformers"] = np.array(deformers, dtype=str).reshape(-1)
    out[f"mesh{i}_shape_counts"] = np.array(counts, np.int64)
    out[f"mesh{i}_shape_index"] = np.concatenate(index) if index else np.zeros(0, np.int64)
    out[f"mesh{i}_shape_offsets"] = np.concatenate(offsets) if offsets else np.zeros((0, 3))
    out[f"mesh{i}_shape_weights"] = np.concatenate(weights) if weights else np.zeros(0)
    return out


def _skin_arrays(i: int, mesh) -> dict:
    """The mesh's first skin deformer: per cluster its bone (an index into the scene's
    nodes), bind matrix (the bone's world matrix at bind time) and sparse vertex weights."""
    bones, binds, counts, index, weights = [], [], [], [], []
    for skin in _elements(mesh.skin_deformers)[:1]:
        for cluster in _elements(skin.clusters):
            if cluster.bone_node is None:
                continue
            bones.append(int(cluster.bone_node.typed_id))
            binds.append(_matrix(cluster.bind_to_world))
            k = np.array(cluster.vertices, np.int64).reshape(-1)
            counts.append(len(k))
            index.append(k)
            weights.append(np.array(cluster.weights, np.float64).reshape(-1))
    return {
        f"mesh{i}_skin_bones": np.array(bones, np.int64),
        f"mesh{i}_skin_binds": np.array(binds, np.float64).reshape(-1, 3, 4),
        f"mesh{i}_skin_counts": np.array(counts, np.int64),
        f"mesh{i}_skin_index": np.concatenate(index) if index else np.zeros(0, np.int64),
        f"mesh{i}_skin_weights": np.concatenate(weights) if weights else np.zeros(0),
    }


def _node_arrays(scene) -> dict:
    """Every node's name, parent (an index into the nodes, -1 for none) and world matrix."""
    nodes = _elements(scene.nodes)
    parents = [int(n.parent.typed_id) if n.parent is not None else -1 for n in nodes]
    return {
        "node_names": np.array([n.name for n in nodes], dtype=str).reshape(-1),
        "node_parents": np.array(parents, np.int64),
        "node_to_world": np.array([_matrix(n.node_to_world) for n in nodes]).reshape(-1, 3, 4),
    }


def main(source: str, target: str) -> None:
    gc.disable()
    try:
        import ufbx
    except ImportError as error:
        sys.stderr.write(f"{error}\n")
        sys.stderr.flush()
        os._exit(4)
    try:
        scene = ufbx.load_file(source, ignore_embedded=True, ignore_animation=True)
    except ufbx.UfbxError as error:
        sys.stderr.write(f"{type(error).__name__}: {error}\n")
        sys.stderr.flush()
        os._exit(3)
    settings = scene.settings
    axes = settings.axes
    arrays = {
        "unit_meters": np.array(float(settings.unit_meters)),
        "axes": np.array([int(axes.right), int(axes.up), int(axes.front)], np.int64),
    }
    arrays.update(_node_arrays(scene))
    meshes = _elements(scene.meshes)
    arrays["n_meshes"] = np.array(len(meshes))
    for i, mesh in enumerate(meshes):
        arrays.update(_mesh_arrays(i, mesh))
    with open(target, "wb") as f:
        np.savez(f, **arrays)
    sys.stdout.flush()
    os._exit(0)  # without freeing the scene


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
