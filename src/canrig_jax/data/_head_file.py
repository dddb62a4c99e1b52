"""Head meshes from files (OBJ, PLY, glTF/GLB through trimesh; FBX), with their length unit.

An OBJ, PLY or glTF file carries no unit. ``load_head`` takes the unit from the caller or
infers it from the bounding box: a human head with some neck, cropped or whole, spans about
15 to 45 cm along its longest side (ICT's head: 33.8 cm, MakeHuman's crop: 3.76 dm). An FBX
file states its unit, and ``load_fbx`` converts it to cm, y up. A unit, stated or the
file's own, that makes the head shorter than 10 cm or taller than 60 cm is refused: a head
3.76 cm tall is a unit mistake, and a rig built on it would be one too.
The ICT raw OBJ folder keeps its own loader (``load_ict_obj_folder``).
"""

import dataclasses
import os
import warnings
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float, Float32, Int, Int32

from .._io import atomic_path, check_output_path
from ._fbx import load_fbx_meshes

HEAD_FORMATS = (".obj", ".ply", ".gltf", ".glb", ".fbx")
"""File extensions ``load_head`` reads."""

HEAD_UNITS_CM = {"mm": 0.1, "cm": 1.0, "dm": 10.0, "m": 100.0}
"""Length of one unit in centimetres (the same table as ``rig.UNIT_IN_CM``)."""

HEAD_SIZE_CM = (15.0, 45.0)
"""Longest bounding-box side of a human head (with some neck) in centimetres: the range
``infer_units`` looks for."""

HEAD_PLAUSIBLE_CM = (10.0, 60.0)
"""Longest bounding-box side a head may have in its stated unit (``load_head`` refuses a
head outside it: the unit is wrong, or the mesh is not a head)."""

_UNIT_WORDS = {"mm": "millimetres", "cm": "centimetres", "dm": "decimetres", "m": "metres"}


@dataclasses.dataclass(frozen=True)
class HeadMesh:
    """A triangle mesh read from a file (``load_head`` lists the fields)."""

    vertices: Float32[np.ndarray, "V 3"]
    faces: Int32[np.ndarray, "F 3"]
    units: str
    inferred: bool
    path: Path

    @property
    def size_cm(self) -> float:
        """Longest bounding-box side in centimetres."""
        extent = self.vertices.max(axis=0) - self.vertices.min(axis=0)
        return float(extent.max()) * HEAD_UNITS_CM[self.units]

    def vertices_in(self, units: str) -> Float32[np.ndarray, "V 3"]:
        """(V, 3) float32 vertices converted to ``units``."""
        if units not in HEAD_UNITS_CM:
            raise ValueError(f"units: expected one of {tuple(HEAD_UNITS_CM)}, got {units!r}")
        scale = HEAD_UNITS_CM[self.units] / HEAD_UNITS_CM[units]
        return (self.vertices.astype(np.float64) * scale).astype(np.float32)


def infer_units(extent: float) -> str | None:
    """The unit in which a longest side of ``extent`` is a head's size, or None."""
    lo, hi = HEAD_SIZE_CM
    for unit, cm in HEAD_UNITS_CM.items():
        if lo <= extent * cm <= hi:
            return unit
    return None


def load_head(path: str | os.PathLike, units: str | None = None) -> HeadMesh:
    """Read a head mesh (OBJ, PLY, glTF, GLB or FBX; a scene's meshes are concatenated).

    Args:
        path: the file.
        units: the file's length unit ("mm", "cm", "dm", "m"); ``None`` infers it from the
            bounding box (a ValueError when no unit gives a head's size), or for FBX takes
            the file's own unit (given, it overrides the file's: its numbers are read in
            ``units``, after the axes and node transforms).

    Returns:
        A ``HeadMesh``: ``vertices`` (V, 3) float32 positions in ``units`` (as stored in the
        file; an FBX file's are turned y up, facing +z, and in cm unless ``units`` was given);
        ``faces`` (F, 3) int32 triangles (polygons fan-split by trimesh or ``load_fbx``);
        ``units``, "mm", "cm", "dm" or "m"; ``inferred``, True when ``units`` was inferred
        from the bounding box; ``path``, the file; ``size_cm``, the longest bounding-box side
        in centimetres; ``vertices_in(units)``, the vertices converted to ``units``.

    Raises FileNotFoundError for a missing file and ValueError naming the file for an empty
    file, an unknown extension, a file that holds no triangle mesh, or non-finite positions;
    and a ValueError naming the file and ``units`` when the stated (or the FBX file's) unit
    makes the longest side shorter than 10 or longer than 60 cm (``HEAD_PLAUSIBLE_CM``),
    with the unit the numbers look like when there is one.
    """
    import trimesh

    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = Path(path)
    if units is not None and units not in HEAD_UNITS_CM:
        raise ValueError(f"units: expected one of {tuple(HEAD_UNITS_CM)}, got {units!r}")
    if not path.exists():
        raise FileNotFoundError(f"path: head file {path} not found")
    if not path.is_file():
        raise ValueError(f"path: {path} is not a file")
    if path.suffix.lower() not in HEAD_FORMATS:
        raise ValueError(
            f"path: {path} has extension {path.suffix!r}, expected one of {HEAD_FORMATS}"
        )
    if path.stat().st_size == 0:
        raise ValueError(f"path: head file {path} is empty")
    if path.suffix.lower() == ".fbx":
        return _fbx_head(path, units)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds on a file that is not a mesh
        raise ValueError(
            f"path: {path} is not a readable mesh ({type(error).__name__}: {error})"
        ) from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"path: {path} holds no triangle mesh (no faces)")
    vertices = np.asarray(loaded.vertices, np.float32)
    faces = np.asarray(loaded.faces, np.int32)
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"path: {path} has non-finite vertex positions")
    extent = float((vertices.max(axis=0) - vertices.min(axis=0)).max())
    if extent <= 0:
        raise ValueError(f"path: {path} has all its vertices at one point")
    inferred = units is None
    if inferred:
        units = infer_units(extent)
        if units is None:
            raise ValueError(
                f"path: {path} spans {extent:.4g} (longest side): no unit of "
                f"{tuple(HEAD_UNITS_CM)} makes that a head's {HEAD_SIZE_CM[0]:g}-"
                f"{HEAD_SIZE_CM[1]:g} cm; give the units"
            )
    else:
        _check_head_size(path, extent, units)
    return HeadMesh(vertices, faces, units, inferred, path)


def _check_head_size(path: Path, extent: float, units: str) -> None:
    """ValueError naming ``path`` and ``units`` when ``extent`` (longest side, in ``units``)
    is not a head's ``HEAD_PLAUSIBLE_CM``."""
    size_cm = extent * HEAD_UNITS_CM[units]
    lo, hi = HEAD_PLAUSIBLE_CM
    if lo <= size_cm <= hi:
        return
    guess = infer_units(extent)
    hint = (
        f"the file looks like {_UNIT_WORDS[guess]}: pass units={guess!r}"
        if guess
        else f"no unit of {tuple(HEAD_UNITS_CM)} makes it a head: is it one (cropped to the "
        f"head and neck)?"
    )
    raise ValueError(
        f"units: {path} is {size_cm:.3g} cm tall (longest side) with units={units!r}; a head "
        f"is {lo:g}-{hi:g} cm tall; {hint}"
    )


def _unit_name(unit_cm: float) -> str:
    """``"cm"`` for 1.0, ... or ``"2.54 cm"`` for a unit outside ``HEAD_UNITS_CM``."""
    name = next((u for u, cm in HEAD_UNITS_CM.items() if abs(cm - unit_cm) <= 1e-9 * cm), None)
    return name or f"{unit_cm:g} cm"


def _fbx_head(path: Path, units: str | None) -> HeadMesh:
    """``load_head`` of an FBX file: every mesh, y up, in cm (or in ``units``, overriding
    the file's unit)."""
    meshes = [m for m in load_fbx_meshes(path) if len(m.triangles)]
    if not meshes:
        raise ValueError(f"path: {path} holds no triangle mesh (no faces)")
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([m.triangles + o for m, o in zip(meshes, offsets, strict=True)])
    extent_cm = float((vertices.max(axis=0) - vertices.min(axis=0)).max())
    if extent_cm <= 0:
        raise ValueError(f"path: {path} has all its vertices at one point")
    if units is not None:  # the file's numbers, read in the caller's unit
        vertices = (vertices.astype(np.float64) / meshes[0].unit_cm).astype(np.float32)
        _check_head_size(path, extent_cm / meshes[0].unit_cm, units)
        return HeadMesh(vertices, faces.astype(np.int32), units, False, path)
    lo, hi = HEAD_PLAUSIBLE_CM
    if not lo <= extent_cm <= hi:
        raise ValueError(
            f"path: {path} is {extent_cm:.3g} cm tall (longest side) in the file's own unit "
            f"({_unit_name(meshes[0].unit_cm)}); a head is {lo:g}-{hi:g} cm tall: crop the "
            f"file to the head and neck, or pass units= if the file states the wrong unit"
        )
    return HeadMesh(vertices, faces.astype(np.int32), "cm", False, path)


def save_obj(
    path: str | os.PathLike, vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Path:
    """Write a triangle mesh as a Wavefront OBJ (positions and faces only), atomically."""
    check_output_path(path)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {faces.shape}")
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return Path(path)
