"""ICT Face Model (USC ICT, MIT licence): neutral head, 53 ARKit-named expressions,
100 identity modes, 17 parts. Units are centimetres.

``load_ict`` reads the ``.npz`` extraction in ``ict-facekit/``; ``load_ict_obj_folder``
reads ICT-FaceKit's original folder format (one OBJ per shape plus
``vertex_indices.json``). ``ICTFaceModel.select`` restricts the model to parts.
"""

import dataclasses
import io
import json
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from jaxtyping import ArrayLike, Bool, Float, Float32, Int, Int32
from scipy.sparse.csgraph import connected_components
from trimesh.exchange.obj import load_obj

from .._io import CorruptFileError
from ._paths import data_file, read_arrays

FACE = ("Face",)
"""The face part alone: vertices 0..9408 (9,409 vertices)."""

ICT_PARTS: tuple[tuple[str, int, int], ...] = (
    ("Face", 0, 9408),
    ("Head and Neck", 9409, 11247),
    ("Mouth socket", 11248, 13293),
    ("Eye socket left", 13294, 13677),
    ("Eye socket right", 13678, 14061),
    ("Gums and tongue", 14062, 17038),
    ("Teeth", 17039, 21450),
    ("Eyeball left", 21451, 23020),
    ("Eyeball right", 23021, 24590),
    ("Lacrimal fluid left", 24591, 24794),
    ("Lacrimal fluid right", 24795, 24998),
    ("Eye blend left", 24999, 25022),
    ("Eye blend right", 25023, 25046),
    ("Eye occlusion left", 25047, 25198),
    ("Eye occlusion right", 25199, 25350),
    ("Eyelashes left", 25351, 26034),
    ("Eyelashes right", 26035, 26718),
)
"""ICT-FaceKit README part table: (name, first vertex, last vertex), both ends inclusive.

The original folder format has no part table, so ``load_ict_obj_folder`` uses this one;
it covers the 26,719 vertices of the ICT Face Model v1 head.
"""


INNER_PARTS = ("Teeth", "Gums and tongue", "Eyeball left", "Eyeball right")
"""Parts that must stay inside the head (what a penetration metric checks)."""

ENCLOSING_PARTS = ("Face", "Head and Neck")
"""The skin: inner parts must stay inside it (winding number >= 1/2; the mouth and eye
sockets are left out — they are oriented towards their cavities, which would cancel the
skin's winding around the teeth)."""


@dataclasses.dataclass(frozen=True)
class ICTFaceModel:
    """The ICT Face Model (or a part selection of it) as host NumPy arrays, centimetres.

    Attributes:
        neutral: (V, 3) float32 neutral head.
        faces: (F, 3) int32 triangles indexing ``neutral``.
        deltas: (K, V, 3) float32 expression offsets from the neutral.
        names: K expression names (ICT's ARKit spelling, ``eyeBlink_L``).
        part_names: names of the parts kept, in vertex order.
        part_vertex_range: (P, 2) half-open vertex range of each kept part.
        component_labels: (V,) connected component of each vertex (original labels).
        landmarks: (L,) Multi-PIE-68 landmark vertices; -1 where the selection dropped one.
        vertex_ids: (V,) index of each vertex in the full 26,719-vertex head.
    """

    neutral: Float32[np.ndarray, "V 3"]
    faces: Int32[np.ndarray, "F 3"]
    deltas: Float32[np.ndarray, "K V 3"]
    names: tuple[str, ...]
    part_names: tuple[str, ...]
    part_vertex_range: Int[np.ndarray, "P 2"]
    component_labels: Int[np.ndarray, " V"]
    landmarks: Int[np.ndarray, " L"]
    vertex_ids: Int[np.ndarray, " V"]

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    def part_mask(
        self, parts: Sequence[str] | str, argument: str = "parts"
    ) -> Bool[np.ndarray, " V"]:
        """(V,) bool: the vertices of the named parts (ValueError naming ``argument`` for an
        empty list or an unknown name)."""
        if isinstance(parts, str):
            parts = (parts,)
        self._check_part_names(parts, argument)
        mask = np.zeros(self.n_vertices, bool)
        for i, name in enumerate(self.part_names):
            if name in parts:
                mask[slice(*self.part_vertex_range[i])] = True
        return mask

    def _check_part_names(self, parts: Sequence[str], argument: str) -> None:
        if not parts:
            raise ValueError(f"{argument}: expected at least one part name")
        unknown = [p for p in parts if p not in self.part_names]
        if unknown:
            raise ValueError(
                f"{argument}: unknown part name(s) {unknown}; known parts are "
                f"{list(self.part_names)}"
            )

    def select(self, parts: Sequence[str] | str | None = FACE) -> "ICTFaceModel":
        """Restrict to a list of part names (``None`` or ``"head"`` keeps all 17 parts).

        Faces are kept when all three corners are kept, and re-indexed.
        """
        if parts is None or parts == "head":
            return self
        if isinstance(parts, str):
            parts = (parts,)
        if not isinstance(parts, Sequence) or not all(isinstance(p, str) for p in parts):
            raise TypeError(f"parts: expected part names (str or a sequence of str), got {parts!r}")
        self._check_part_names(parts, "parts")
        order = [i for i, name in enumerate(self.part_names) if name in set(parts)]
        keep = np.concatenate([np.arange(*self.part_vertex_range[i]) for i in order]).astype(
            np.int64
        )
        new_index = np.full(self.n_vertices, -1, dtype=np.int64)
        new_index[keep] = np.arange(keep.size)
        face_kept = np.all(new_index[self.faces] >= 0, axis=1)
        sizes = np.diff(self.part_vertex_range[order], axis=1)[:, 0]
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        landmarks = np.where(self.landmarks >= 0, new_index[self.landmarks], -1)
        return ICTFaceModel(
            neutral=self.neutral[keep],
            faces=new_index[self.faces[face_kept]].astype(np.int32),
            deltas=self.deltas[:, keep],
            names=self.names,
            part_names=tuple(self.part_names[i] for i in order),
            part_vertex_range=np.stack([starts, starts + sizes], axis=1).astype(np.int32),
            component_labels=self.component_labels[keep],
            landmarks=landmarks.astype(np.int32),
            vertex_ids=self.vertex_ids[keep],
        )


def load_ict(
    data_dir: str | os.PathLike | None = None, parts: Sequence[str] | str | None = None
) -> ICTFaceModel:
    """Load the ICT Face Model from ``ict-facekit/expressions.npz``.

    Args:
        data_dir: data folder (else ``$CANRIG_DATA``, else ``../shared/data``).
        parts: part names to keep (``FACE`` for the 9,409-vertex face); ``None`` keeps
            the whole 26,719-vertex head.
    """
    path = data_file("ict-facekit/expressions.npz", data_dir)
    keys = ("neutral", "faces", "deltas", "names", "part_names", "part_vertex_range")
    keys += ("component_labels", "landmarks_multipie68")
    z = read_arrays(path, keys)
    _check_shapes(path, z)
    model = ICTFaceModel(
        neutral=z["neutral"].astype(np.float32),
        faces=z["faces"].astype(np.int32),
        deltas=z["deltas"].astype(np.float32),
        names=tuple(str(n) for n in z["names"]),
        part_names=tuple(str(n) for n in z["part_names"]),
        part_vertex_range=z["part_vertex_range"].astype(np.int32),
        component_labels=z["component_labels"].astype(np.int32),
        landmarks=z["landmarks_multipie68"].astype(np.int32),
        vertex_ids=np.arange(z["neutral"].shape[0], dtype=np.int32),
    )
    return model.select(parts)


def load_identity_modes(
    data_dir: str | os.PathLike | None = None,
) -> Float32[np.ndarray, "100 V 3"]:
    """The (100, 26719, 3) float32 identity PCA modes, offsets from the neutral (cm)."""
    path = data_file("ict-facekit/identity.npz", data_dir)
    modes = read_arrays(path, ("identity_deltas",))["identity_deltas"]
    if modes.ndim != 3 or modes.shape[2] != 3:
        raise CorruptFileError(f"{path}: identity_deltas has shape {modes.shape}, not (N, V, 3)")
    return modes.astype(np.float32)


def ict_identity(
    coefficients: Float[ArrayLike, " n"],
    data_dir: str | os.PathLike | None = None,
    model: ICTFaceModel | None = None,
) -> Float32[np.ndarray, "V 3"]:
    """Neutral head of an identity: neutral + sum_i c_i mode_i (cm).

    Args:
        coefficients: (n,) with n <= 100, weights of the first n identity modes, drawn
            from a standard normal in the kit's own ``randomize_identity``.
        model: a (possibly part-selected) model whose vertices to return; default whole head.

    Returns:
        (V, 3) float32 neutral vertices of that identity, V as in ``model``.
    """
    coefficients = np.asarray(coefficients, dtype=np.float64)
    if coefficients.ndim != 1 or not 1 <= coefficients.size <= 100:
        raise ValueError(
            f"coefficients: expected a 1-D array of 1 to 100 identity weights, "
            f"got shape {coefficients.shape}"
        )
    if not np.all(np.isfinite(coefficients)):
        raise ValueError("coefficients: contains non-finite values")
    model = load_ict(data_dir) if model is None else model
    modes = load_identity_modes(data_dir)[: coefficients.size][:, model.vertex_ids]
    offset = np.tensordot(coefficients, modes, axes=1)
    return (model.neutral + offset).astype(np.float32)


def _check_shapes(path: Path, z: dict) -> None:
    """Consistency of the arrays of ``expressions.npz`` (a damaged file says so, by name)."""
    neutral, faces, deltas = z["neutral"], z["faces"], z["deltas"]
    problems = []
    if neutral.ndim != 2 or neutral.shape[1:] != (3,):
        problems.append(f"neutral has shape {neutral.shape}")
    elif deltas.ndim != 3 or deltas.shape[1:] != neutral.shape:
        problems.append(f"deltas has shape {deltas.shape} for a neutral of {neutral.shape}")
    if faces.ndim != 2 or faces.shape[1:] != (3,):
        problems.append(f"faces has shape {faces.shape}")
    elif faces.size and (faces.min() < 0 or faces.max() >= len(neutral)):
        problems.append("faces index outside the vertices")
    if len(z["names"]) != len(deltas):
        problems.append(f"{len(z['names'])} names for {len(deltas)} deltas")
    if not np.all(np.isfinite(neutral)) or not np.all(np.isfinite(deltas)):
        problems.append("non-finite positions")
    if problems:
        raise CorruptFileError(f"{path}: corrupt data file ({'; '.join(problems)})")


def _read_obj(path: Path, with_polygons: bool = False) -> tuple[np.ndarray, list[list[int]]]:
    """Vertices (N, 3) float64 of an OBJ in file order, and its ``f`` records (0-based).

    Positions are parsed by trimesh. ``maintain_order=True`` keeps file order, but trimesh
    splits the mesh into one geometry per ``usemtl`` group, each holding the vertex prefix
    its faces reach; the longest prefix is the whole vertex list. trimesh also triangulates
    mixed tri/quad groups in its own order, so polygons are read from the ``f`` lines here.
    """
    text = path.read_text()
    damaged = f"folder: {path} is truncated or damaged"
    try:
        with warnings.catch_warnings():  # trimesh's UV code warns on the all-NaN material slices
            warnings.simplefilter("ignore", RuntimeWarning)
            loaded = load_obj(
                io.StringIO(text), maintain_order=True, skip_materials=True, group_material=False
            )
        geometries = loaded.get("geometry", {}) if isinstance(loaded, dict) else {}
    except (KeyError, IndexError, ValueError) as error:  # trimesh on a cut or damaged file
        raise CorruptFileError(f"{damaged} ({type(error).__name__}: {error})") from error
    if not geometries:
        raise CorruptFileError(f"{damaged}: no faces (an OBJ head has vertices and faces)")
    vertices = max((g["vertices"] for g in geometries.values()), key=len)
    n_records = sum(1 for line in text.splitlines() if line.startswith("v "))
    if len(vertices) != n_records:
        raise CorruptFileError(
            f"{damaged}: its faces reach {len(vertices)} of its {n_records} vertices"
        )
    polygons = []
    if with_polygons:
        for line in text.splitlines():
            if line.startswith("f "):
                polygons.append([int(token.split("/")[0]) - 1 for token in line.split()[1:]])
    return np.asarray(vertices, dtype=np.float64), polygons


def _fan_triangulate(polygons: list[list[int]], n_vertices: int) -> np.ndarray:
    """(F, 3) int32 triangles: polygon (a, b, c, d, ...) -> (a, b, c), (a, c, d), ..."""
    triangles = [
        (poly[0], poly[i], poly[i + 1]) for poly in polygons for i in range(1, len(poly) - 1)
    ]
    faces = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise ValueError(f"faces: vertex indices must lie in [0, {n_vertices}) (1-based in OBJ)")
    return faces.astype(np.int32)


def _component_labels(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) int32 connected component of each vertex on the face (edge) graph."""
    rows = faces[:, [0, 1, 2]].ravel()
    cols = faces[:, [1, 2, 0]].ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, n_vertices))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int32)


def load_ict_obj_folder(
    folder: str | os.PathLike, names: Sequence[str] | None = None
) -> ICTFaceModel:
    """Load ICT-FaceKit's original format: one OBJ per shape plus ``vertex_indices.json``.

    The folder holds ``generic_neutral_mesh.obj``, ``<expression>.obj`` per blendshape
    (same vertex order) and ``vertex_indices.json`` (keys ``expressions``,
    ``idx_to_landmark_verts``, ...). Deltas are ``expression - neutral`` as in the kit's
    ``face_model_io.py``; polygons (quads and triangles) are fan-split like
    ``expressions.npz``; parts come from ``ICT_PARTS``.

    Args:
        folder: the ICT-FaceKit ``FaceXModel`` folder (or a copy with fewer OBJs).
        names: expressions to load, in this order. ``None`` loads every expression listed
            in ``vertex_indices.json`` whose OBJ is present in ``folder``.

    Returns:
        The full head (V = 26,719): neutral (V, 3) and deltas (K, V, 3) float32 in cm.

    Raises:
        FileNotFoundError: ``folder``, the neutral, the JSON or a requested OBJ is missing.
        ValueError: an expression OBJ's vertex count differs from the neutral's, or the
            head does not have the vertex count ``ICT_PARTS`` describes.
        CorruptFileError: (a ValueError) an OBJ is truncated or damaged; names the file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"folder: ICT-FaceKit model folder {folder} not found")
    for required in ("generic_neutral_mesh.obj", "vertex_indices.json"):
        if not (folder / required).is_file():
            raise FileNotFoundError(f"folder: expected {required} in {folder}, not found")
    indices = json.loads((folder / "vertex_indices.json").read_text())
    if names is None:
        names = [n for n in indices["expressions"] if (folder / f"{n}.obj").is_file()]
    else:
        names = [names] if isinstance(names, str) else list(names)
        missing = [n for n in names if not (folder / f"{n}.obj").is_file()]
        if missing:
            raise FileNotFoundError(f"names: no OBJ in {folder} for expression(s) {missing}")

    neutral, polygons = _read_obj(folder / "generic_neutral_mesh.obj", with_polygons=True)
    n_vertices = neutral.shape[0]
    if n_vertices != ICT_PARTS[-1][2] + 1:
        raise ValueError(
            f"folder: neutral has {n_vertices} vertices, ICT_PARTS describes {ICT_PARTS[-1][2] + 1}"
        )
    deltas = np.zeros((len(names), n_vertices, 3), dtype=np.float32)
    for k, name in enumerate(names):
        shape, _ = _read_obj(folder / f"{name}.obj")
        if shape.shape != neutral.shape:
            raise ValueError(
                f"names: {name}.obj has {shape.shape[0]} vertices, the neutral {n_vertices}"
            )
        deltas[k] = shape - neutral
    faces = _fan_triangulate(polygons, n_vertices)
    return ICTFaceModel(
        neutral=neutral.astype(np.float32),
        faces=faces,
        deltas=deltas,
        names=tuple(names),
        part_names=tuple(name for name, _, _ in ICT_PARTS),
        part_vertex_range=np.array([(a, b + 1) for _, a, b in ICT_PARTS], dtype=np.int32),
        component_labels=_component_labels(faces, n_vertices),
        landmarks=np.asarray(indices["idx_to_landmark_verts"], dtype=np.int32),
        vertex_ids=np.arange(n_vertices, dtype=np.int32),
    )
