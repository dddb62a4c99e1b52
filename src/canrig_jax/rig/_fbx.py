"""A ``BlendshapeRig`` from an FBX file's blend shapes (Maya, 3ds Max, Blender, Unreal)."""

import os

import numpy as np

from ..data import arkit_name_of, load_fbx
from ..mesh import connected_components
from ._blendshape import BlendshapeRig

_HEAD_MARGIN_CM = 6.0
"""``crop="head"`` keeps this much below the lowest moving vertex (the neck)."""

_MOVED_CM = 1e-3
"""A vertex moves when some kept shape offsets it by more than this (exporters leave
offsets of a few 1e-5 cm on vertices a shape does not move)."""

_NAMES = ("arkit-only", "all")
"""Values of ``load_fbx_rig``'s ``names``."""

_CROPS = (None, "head")
"""Values of ``load_fbx_rig``'s ``crop``."""


def _head_region(vertices: np.ndarray, faces: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Sorted indices of the head: vertices above the lowest moving one minus the margin (y
    up), in faces wholly inside, in components that move or lie in the moving region's box
    (the eyes of a rig whose eye shapes are bone-driven)."""
    moving = np.linalg.norm(deltas, axis=-1).max(axis=0) > _MOVED_CM
    if not moving.any():
        raise ValueError(f"crop: no shape moves a vertex by more than {_MOVED_CM} cm")
    above = vertices[:, 1] >= vertices[moving, 1].min() - _HEAD_MARGIN_CM
    inside = faces[above[faces].all(axis=1)]
    used = np.zeros(len(vertices), bool)
    used[inside.ravel()] = True
    labels = connected_components(inside, len(vertices))
    lo, hi = vertices[moving].min(axis=0), vertices[moving].max(axis=0)
    in_box = np.all((vertices >= lo) & (vertices <= hi), axis=1)
    keep = np.zeros(len(vertices), bool)
    for label in np.unique(labels[used]):
        members = used & (labels == label)
        if moving[members].any() or in_box[members].all():
            keep |= members
    return np.flatnonzero(keep)


def load_fbx_rig(
    path: str | os.PathLike,
    *,
    mesh: str | None = None,
    names: str = "arkit-only",
    crop: str | None = None,
) -> BlendshapeRig:
    """A linear ``BlendshapeRig`` (cm, y up, facing +z) from one mesh of an FBX file.

    The mesh, its triangles and its dense blend-shape deltas come from ``data.load_fbx``
    (unit, axes and node transform applied). Shape names that ``data.arkit_name_of``
    recognises (``AK_25_JawOpen``, ``JawOpen``, ``blendShape1.jawOpen``) become ARKit
    camelCase (``jawOpen``), so the rig drives from ARKit / Live Link Face weights.

    Args:
        path: a binary or ASCII ``.fbx`` file.
        mesh: the mesh's name; ``None`` takes the one with the most blend shapes.
        names: ``"arkit-only"`` keeps the ARKit shapes (in file order), ``"all"`` keeps
            every shape (ARKit ones renamed, the others as in the file).
        crop: ``None`` keeps the whole mesh; ``"head"`` keeps the vertices above the lowest
            vertex a kept shape moves (by over 10 um) minus 6 cm (the neck), the faces
            wholly inside, and of those the connected parts that move or lie inside the
            moving region's box (eyes), vertices in file order.

    Raises ValueError naming the argument for an unknown ``names``/``crop``, a file with no
    ARKit shape under ``names="arkit-only"``, two shapes with one ARKit name, and the
    errors of ``load_fbx`` (a file that is not FBX, an unknown ``mesh``, ...).
    """
    if names not in _NAMES:
        raise ValueError(f"names: expected one of {_NAMES}, got {names!r}")
    if crop not in _CROPS:
        raise ValueError(f"crop: expected one of {_CROPS}, got {crop!r}")
    fbx = load_fbx(path, mesh=mesh)
    arkit = [arkit_name_of(n) for n in fbx.names]
    if names == "arkit-only":
        keep = [i for i, a in enumerate(arkit) if a is not None]
        if not keep:
            raise ValueError(
                f"names: {fbx.path} mesh {fbx.name!r} has no ARKit blend shape among its "
                f"{fbx.n_blendshapes} ({list(fbx.names[:5])}...); pass names='all'"
            )
    else:
        keep = list(range(fbx.n_blendshapes))
    rig_names = [arkit[i] or fbx.names[i] for i in keep]
    seen: dict[str, list[str]] = {}
    for i, name in zip(keep, rig_names, strict=True):
        seen.setdefault(name, []).append(fbx.names[i])
    clashes = {k: v for k, v in seen.items() if len(v) > 1}
    if clashes:
        raise ValueError(
            f"names: {fbx.path} mesh {fbx.name!r} has several shapes for one ARKit name: {clashes}"
        )
    vertices, faces = fbx.vertices, fbx.triangles
    deltas = fbx.deltas[keep]
    if crop == "head":
        kept = _head_region(vertices, faces, deltas)
        new_index = np.full(len(vertices), -1, np.int64)
        new_index[kept] = np.arange(kept.size)
        faces = new_index[faces[(new_index[faces] >= 0).all(axis=1)]].astype(np.int32)
        vertices, deltas = vertices[kept], deltas[:, kept]
    return BlendshapeRig(vertices, deltas, (), tuple(rig_names), faces, units="cm")
