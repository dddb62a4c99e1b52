"""Meshes and blend shapes from Autodesk FBX files (binary or ASCII), through ``ufbx``.

Rigs arrive from Maya, 3ds Max, Blender and Unreal as FBX. ``load_fbx`` reads one mesh of a
file with its blend shapes, in the package's frame: **centimetres, y up, facing +z**,
whatever the file's unit and axes. A position ``p`` of the file becomes

    p_cm = (100 * unit_m) * R_axes @ (A @ p + t)

where ``(A, t)`` is the mesh node's geometry-to-world transform (the node hierarchy and the
geometric offset; 3ds Max's exporter puts its z-up to y-up turn there), ``R_axes`` turns the
file's (right, up, front) axes of ``GlobalSettings`` onto (+x, +y, +z), and ``unit_m`` is the
file's ``UnitScaleFactor`` in metres (0.01 for cm). A blend-shape delta gets the same linear
map without ``t``. A mirroring map (left-handed axes, a negative scale) reverses the
triangles' winding so that they keep facing outwards.

The reader is ufbx (https://ufbx.github.io/, MIT; the ``ufbx`` wheels on PyPI, 0.0.5), run in a
child process (``_fbx_child.py``) that copies the file's arrays out: those bindings are not
memory-safe when a scene is freed, and a process of their own keeps that away from the caller.
"""

import dataclasses
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from jaxtyping import Float32, Float64, Int, Int32

from .._io import CorruptFileError

_BINARY_MAGIC = b"Kaydara FBX Binary  \x00"
_ASCII_MARKERS = (b"FBXHeaderExtension", b"; FBX ")

_AXIS_VECTORS = {  # ufbx.CoordinateAxis value -> unit vector
    0: (1.0, 0.0, 0.0),
    1: (-1.0, 0.0, 0.0),
    2: (0.0, 1.0, 0.0),
    3: (0.0, -1.0, 0.0),
    4: (0.0, 0.0, 1.0),
    5: (0.0, 0.0, -1.0),
}
_AXIS_NAMES = {0: "+x", 1: "-x", 2: "+y", 3: "-y", 4: "+z", 5: "-z"}


@dataclasses.dataclass(frozen=True)
class FbxSkin:
    """A mesh's skin (its first skin deformer), in the package's frame (cm, y up).

    Attributes:
        bones: (J,) int the bone of each joint, an index into ``FbxScene.node_names``.
        bind_to_world: (J, 4, 4) float64 each bone's world matrix at bind time, in the
            package's frame (``C B C^-1`` for the file's matrix ``B`` and the conversion ``C``
            of the module docstring), so that ``bind_to_world[j]^-1 @ vertex`` is the vertex in
            the bone's frame.
        joints: (V, M) int32 the joints (indices into ``bones``) of each vertex, M the most any
            vertex has; unused slots hold 0 with weight 0.
        weights: (V, M) float32 the joints' weights, as stored (not renormalised).
    """

    bones: Int[np.ndarray, " J"]
    bind_to_world: Float64[np.ndarray, "J 4 4"]
    joints: Int32[np.ndarray, "V M"]
    weights: Float32[np.ndarray, "V M"]


@dataclasses.dataclass(frozen=True)
class FbxMesh:
    """One mesh of an FBX file with its blend shapes, in centimetres, y up, facing +z.

    Attributes:
        name: the mesh's node name (the geometry's own name when no node instances it).
        vertices: (V, 3) float32 rest positions, cm, y up; one row per FBX control point,
            in the file's order (an index into the file's vertex list stays valid).
        triangles: (F, 3) int32 triangles, the polygons fan-split in file order
            (polygon ``(a, b, c, d)`` gives ``(a, b, c), (a, c, d)``); points and lines dropped.
        names: S blend-shape channel names, the blend-shape node's prefix removed
            (``blendShape1.AK_25_JawOpen`` gives ``AK_25_JawOpen``) unless that makes two equal.
        deltas: (S, V, 3) float32 offsets at full weight, cm, in the same frame as
            ``vertices`` (the file stores them sparsely; vertices a shape leaves alone get 0).
        path: the file.
        unit_cm: length of the file's unit in centimetres (its ``UnitScaleFactor``; 1 for cm).
        axes: the file's (right, up, front) axes as stored, e.g. ``("+x", "+y", "+z")``.
        meshes: names of every mesh in the file, in file order.
    """

    name: str
    vertices: Float32[np.ndarray, "V 3"]
    triangles: Int32[np.ndarray, "F 3"]
    names: tuple[str, ...]
    deltas: Float32[np.ndarray, "S V 3"]
    path: Path
    unit_cm: float
    axes: tuple[str, str, str]
    meshes: tuple[str, ...]
    node: int = -1
    skin: FbxSkin | None = None

    @property
    def n_blendshapes(self) -> int:
        return len(self.names)


@dataclasses.dataclass(frozen=True)
class FbxScene:
    """Every mesh of an FBX file with its skin, and the file's node tree (its skeleton), all
    in the package's frame (cm, y up, facing +z); ``load_fbx_scene`` lists the fields."""

    meshes: tuple[FbxMesh, ...]
    node_names: tuple[str, ...]
    node_parents: Int[np.ndarray, " N"]
    node_to_world: Float64[np.ndarray, "N 4 4"]
    path: Path


def _check_fbx_path(path) -> Path:
    """``path`` as a Path after the checks that need no parsing (exists, a file, FBX header)."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"path: FBX file {path} not found")
    if not path.is_file():
        raise ValueError(f"path: {path} is not a file")
    size = path.stat().st_size
    if size == 0:
        raise ValueError(f"path: FBX file {path} is empty")
    with open(path, "rb") as f:
        head = f.read(1024)
    if head.startswith(_BINARY_MAGIC[:18]):
        if len(head) < 27 or not head.startswith(_BINARY_MAGIC):
            raise CorruptFileError(f"path: corrupt FBX file {path} (truncated header)")
    elif not any(marker in head for marker in _ASCII_MARKERS):
        raise ValueError(
            f"path: {path} is not an FBX file (neither the binary header "
            f"'Kaydara FBX Binary' nor an ASCII FBX header in its first bytes)"
        )
    return path


def _read_raw(path: Path) -> dict[str, np.ndarray]:
    """The file's raw arrays, as ``_fbx_child.py`` writes them (no conversion)."""
    child = Path(__file__).with_name("_fbx_child.py")
    with tempfile.TemporaryDirectory(prefix="canrig_fbx_") as folder:
        target = Path(folder) / "raw.npz"
        done = subprocess.run(
            [sys.executable, str(child), str(path), str(target)],
            capture_output=True,
            encoding="utf-8",
            errors="replace",
            check=False,
        )
        message = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""
        if done.returncode == 4:
            raise ImportError(
                f"reading FBX files needs the ufbx package ({message}): pip install ufbx"
            )
        if done.returncode == 3:
            raise CorruptFileError(f"path: {path} is not a readable FBX file ({message})")
        if done.returncode != 0 or not target.is_file():
            raise CorruptFileError(
                f"path: the FBX reader stopped on {path} (exit status {done.returncode}"
                f"{': ' + message if message else ''}): a damaged or unsupported file"
            )
        with np.load(target, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}


def _fan_triangles(corners: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, 3) fan split of polygons given by (F, 2) (first corner, corner count) rows."""
    begin, count = faces[:, 0].astype(np.int64), faces[:, 1].astype(np.int64)
    per_face = np.maximum(count - 2, 0)
    owner = np.repeat(np.arange(len(faces)), per_face)
    first_of_owner = np.concatenate([[0], np.cumsum(per_face)[:-1]])[owner]
    k = np.arange(owner.size) - first_of_owner
    start = begin[owner]
    tri = np.stack([corners[start], corners[start + 1 + k], corners[start + 2 + k]], axis=1)
    return tri.astype(np.int32).reshape(-1, 3)


def _mesh_name(raw: dict, i: int) -> str:
    for candidate in [*raw[f"mesh{i}_nodes"].tolist(), str(raw[f"mesh{i}_name"])]:
        if candidate:
            return candidate
    return f"mesh{i}"


def _read_mesh(path: Path, raw: dict, i: int, name: str, axes_map, unit_cm, context) -> FbxMesh:
    """One mesh of the raw arrays, converted (module docstring)."""
    to_world = raw[f"mesh{i}_to_world"]
    linear = unit_cm * (axes_map @ to_world[:, :3])
    shift = unit_cm * (axes_map @ to_world[:, 3])
    control = raw[f"mesh{i}_vertices"]
    n = len(control)
    vertices = control @ linear.T + shift
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"path: {path} mesh {name!r} has non-finite vertex positions")
    corners, faces = raw[f"mesh{i}_corners"], raw[f"mesh{i}_faces"]
    if corners.size and (corners.min() < 0 or corners.max() >= n):
        raise CorruptFileError(f"path: corrupt FBX file {path} (mesh {name!r} face indices)")
    if faces.size and (faces[:, 0] + faces[:, 1]).max() > corners.size:
        raise CorruptFileError(f"path: corrupt FBX file {path} (mesh {name!r} faces)")
    triangles = _fan_triangles(corners, faces)
    if np.linalg.det(linear) < 0:  # a mirror: keep the triangles facing outwards
        triangles = triangles[:, ::-1].copy()
    full = raw[f"mesh{i}_shape_names"].tolist()
    prefixes = [d + "." if d else "" for d in raw[f"mesh{i}_shape_deformers"].tolist()]
    pairs = zip(full, prefixes, strict=True)
    bare = [s[len(p) :] if p and s.startswith(p) else s for s, p in pairs]
    names = bare if len(set(bare)) == len(bare) else full
    counts = raw[f"mesh{i}_shape_counts"]
    index = raw[f"mesh{i}_shape_index"]
    offsets = raw[f"mesh{i}_shape_offsets"] * raw[f"mesh{i}_shape_weights"][:, None]
    if index.size and (index.min() < 0 or index.max() >= n):
        raise CorruptFileError(f"path: corrupt FBX file {path} (mesh {name!r} shape indices)")
    deltas = np.zeros((len(full), n, 3), np.float32)
    ends = np.cumsum(counts)
    for s, (start, end) in enumerate(zip(ends - counts, ends, strict=True)):
        dense = np.zeros((n, 3), np.float64)
        np.add.at(dense, index[start:end], offsets[start:end])
        deltas[s] = dense @ linear.T
    if not np.all(np.isfinite(deltas)):
        raise ValueError(f"path: {path} mesh {name!r} has non-finite blend-shape offsets")
    return FbxMesh(
        node=int(raw.get(f"mesh{i}_node", -1)),
        skin=_read_skin(path, raw, i, name, n, axes_map, unit_cm),
        name=name,
        vertices=vertices.astype(np.float32),
        triangles=triangles,
        names=tuple(names),
        deltas=deltas,
        path=path,
        **context,
    )


def _conjugate(matrices: np.ndarray, axes_map: np.ndarray, unit_cm: float) -> np.ndarray:
    """(N, 4, 4) ``C M C^-1`` of (N, 3, 4) file matrices ``M``, ``C = unit_cm * R_axes``."""
    full = np.zeros((len(matrices), 4, 4))
    full[:, :3, :] = matrices
    full[:, 3, 3] = 1.0
    c = np.eye(4)
    c[:3, :3] = unit_cm * axes_map
    return c @ full @ np.linalg.inv(c)


def _read_skin(path, raw: dict, i: int, name: str, n: int, axes_map, unit_cm) -> FbxSkin | None:
    bones = raw.get(f"mesh{i}_skin_bones")
    if bones is None or bones.size == 0:
        return None
    counts, index = raw[f"mesh{i}_skin_counts"], raw[f"mesh{i}_skin_index"]
    weight = raw[f"mesh{i}_skin_weights"]
    if index.size and (index.min() < 0 or index.max() >= n) or weight.size != index.size:
        raise CorruptFileError(f"path: corrupt FBX file {path} (mesh {name!r} skin weights)")
    joint_of = np.repeat(np.arange(len(bones)), counts)
    slots = np.zeros(n, np.int64)
    width = int(np.bincount(index, minlength=n).max()) if index.size else 1
    joints = np.zeros((n, max(width, 1)), np.int32)
    weights = np.zeros((n, max(width, 1)), np.float32)
    for vertex, joint, w in zip(index, joint_of, weight, strict=True):
        joints[vertex, slots[vertex]] = joint
        weights[vertex, slots[vertex]] = w
        slots[vertex] += 1
    binds = _conjugate(raw[f"mesh{i}_skin_binds"], axes_map, unit_cm)
    return FbxSkin(bones.astype(np.int64), binds, joints, weights)


def load_fbx_scene(path: str | os.PathLike) -> FbxScene:
    """Every mesh of an FBX file with its skin weights, and the file's node tree (its
    skeleton), in cm, y up, facing +z (the conversion and errors of ``load_fbx``).

    Returns:
        An ``FbxScene``: ``meshes``, every mesh in file order (each as ``load_fbx`` returns
        it, with its ``skin`` and its ``node``, an index into ``node_names``); ``node_names``,
        the N node names (the scene's root node first, usually named ``""``);
        ``node_parents`` (N,) int, the parent of each node, -1 for the root;
        ``node_to_world`` (N, 4, 4) float64, each node's world matrix in the scene's own pose
        (converted like the skin's ``bind_to_world``); ``path``, the file.
    """
    path = _check_fbx_path(path)
    raw = _read_raw(path)
    meshes, axes_map, unit_cm = _convert_meshes(path, raw)
    return FbxScene(
        meshes=meshes,
        node_names=tuple(str(n) for n in raw["node_names"]),
        node_parents=raw["node_parents"].astype(np.int64),
        node_to_world=_conjugate(raw["node_to_world"], axes_map, unit_cm),
        path=path,
    )


def load_fbx_meshes(path: str | os.PathLike) -> tuple[FbxMesh, ...]:
    """Every mesh of an FBX file (binary or ASCII), in file order, each in cm, y up, facing
    +z, with its blend shapes (see ``load_fbx`` for the conversion and the errors)."""
    path = _check_fbx_path(path)
    return _convert_meshes(path, _read_raw(path))[0]


def _convert_meshes(path: Path, raw: dict):
    """(the meshes, the axes map, the unit in cm) of the raw arrays."""
    unit_m = float(raw["unit_meters"])
    if not (np.isfinite(unit_m) and unit_m > 0):
        raise CorruptFileError(f"path: {path} states a unit scale of {unit_m} m")
    stored = tuple(int(a) for a in raw["axes"])
    if any(a not in _AXIS_VECTORS for a in stored) or len({a // 2 for a in stored}) != 3:
        raise CorruptFileError(f"path: {path} states unusable axes {stored}")
    axes_map = np.array([_AXIS_VECTORS[a] for a in stored], np.float64)  # rows: new x, y, z
    count = int(raw["n_meshes"])
    names = tuple(_mesh_name(raw, i) for i in range(count))
    context = {
        "unit_cm": unit_m * 100.0,
        "axes": tuple(_AXIS_NAMES[a] for a in stored),
        "meshes": names,
    }
    meshes = tuple(
        _read_mesh(path, raw, i, names[i], axes_map, unit_m * 100.0, context) for i in range(count)
    )
    return meshes, axes_map, unit_m * 100.0


def _listing(meshes: tuple[FbxMesh, ...]) -> str:
    return ", ".join(
        f"{m.name!r} ({len(m.vertices)} vertices, {m.n_blendshapes} blend shapes)" for m in meshes
    )


def load_fbx(path: str | os.PathLike, *, mesh: str | None = None) -> FbxMesh:
    """One mesh of an FBX file with its blend shapes, in centimetres, y up, facing +z.

    The file's unit (``UnitScaleFactor``), axes (``UpAxis``/``FrontAxis``/``CoordAxis``) and
    the mesh node's transform are applied: ``p_cm = 100 unit_m R_axes (A p + t)``, deltas
    without ``t`` (module docstring). A mesh instanced by several nodes takes the first
    node's transform. Blend shapes are dense at full weight, each channel's target shape
    times its per-vertex weights; in-between shapes are not read.

    Args:
        path: a binary or ASCII ``.fbx`` file.
        mesh: the mesh's name (its node's name, as ``FbxMesh.meshes`` lists them); ``None``
            takes the mesh with the most blend shapes.

    Returns:
        An ``FbxMesh``: ``vertices`` (V, 3) and ``deltas`` (S, V, 3) float32 cm, ``triangles``
        (F, 3) int32, ``names`` (S,).

    Raises FileNotFoundError for a missing file; ValueError naming the file (a
    ``CorruptFileError`` for damaged bytes) for an empty, truncated or non-FBX file, a file
    with no mesh, an unknown ``mesh`` name, or several meshes tied for the most blend shapes
    with ``mesh=None`` (the error lists the meshes).
    """
    if mesh is not None and not isinstance(mesh, str):
        raise TypeError(f"mesh: expected a mesh name or None, got {type(mesh).__name__}")
    meshes = load_fbx_meshes(path)
    path = Path(path)
    if not meshes:
        raise ValueError(f"path: {path} holds no mesh")
    if mesh is not None:
        chosen = [m for m in meshes if m.name == mesh]
        if not chosen:
            raise ValueError(f"mesh: {path} has no mesh {mesh!r}; its meshes: {_listing(meshes)}")
        if len(chosen) > 1:
            raise ValueError(
                f"mesh: {path} has {len(chosen)} meshes named {mesh!r}; its meshes: "
                f"{_listing(meshes)}"
            )
        return chosen[0]
    most = max(m.n_blendshapes for m in meshes)
    chosen = [m for m in meshes if m.n_blendshapes == most]
    if len(chosen) > 1:
        raise ValueError(
            f"mesh: {path} holds {len(chosen)} meshes with {most} blend shapes each, pass "
            f"mesh=NAME to choose one; its meshes: {_listing(meshes)}"
        )
    return chosen[0]
