"""Your avatar in, the same avatar with a face rig out.

``auto_rig_avatar`` takes a whole avatar (``.glb``, ``.vrm`` or ``.fbx``: skeleton, skin
weights, body, head, eyes, teeth, clothes), finds its head, rigs the face meshes together with
``auto_rig`` (in the bind pose, in centimetres) and writes the shapes as morph targets into the
avatar itself (``rig.add_morph_targets``: everything else kept byte for byte). An FBX avatar is
first written as a glTF avatar (``rig.avatar_from_fbx``: nodes, meshes, skins), then rigged the
same way.

The head: the skeleton's head bone (a node whose name ends in ``head`` after a prefix such as
``mixamorig:``, ``Bip01 `` or ``J_Bip_C_``; the VRM humanoid's ``head`` when stated) and every
node below it (jaw, eyes, tongue). Face vertices: those whose skin weights on the head's bones
sum above ``HEAD_WEIGHT``, and every vertex of an unskinned mesh hung under the head. Meshes
named like hair, hats or glasses are not rigged. An avatar without a head bone is rigged whole
when it is head-sized (``data.HEAD_PLAUSIBLE_CM``); a standing body (``BODY_HEIGHT_CM`` tall,
+y up, as glTF stores it) gives its head by geometry (``HEAD_OF_BODY``); anything else is
refused with what to do, before any compiled work.
"""

import dataclasses
import os
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..data import HEAD_PLAUSIBLE_CM, load_fbx_scene
from ..rig import (
    EXTRA_SHAPES,
    GltfAvatar,
    add_morph_targets,
    add_vrm_expressions,
    avatar_from_fbx,
    check_extra_sets,
    check_humanoid,
    mesh_vertices,
    node_descendants,
    read_gltf_avatar,
    target_names,
    with_extra_shapes,
    write_gltf_avatar,
)
from ..rig._gltf_avatar import scene_nodes
from ._any_head import auto_rig, check_auto_rig
from ._methods import AbstractAutoRigMethod
from ._rig_checks import RigCheck, failed_hard_checks

AVATAR_FORMATS = (".glb", ".vrm", ".fbx")
"""Avatar files ``auto_rig_avatar`` reads."""

MAX_FACE_VERTICES = 200_000
"""The most face vertices rigged (a larger face is refused before any compiled work)."""

METRES_TO_CM = 100.0

HEAD_WEIGHT = 0.5
"""A skinned vertex is the face's when its weights on the head's bones sum above this."""

BODY_HEIGHT_CM = (100.0, 250.0)
"""An avatar without a head bone this tall (+y, cm) is a standing body: its head is found by
geometry (``HEAD_OF_BODY``)."""

HEAD_OF_BODY = (0.15, 0.12)
"""A standing body's head without a head bone: the vertices in the top 15 % of its height and
within 12 % of its height (horizontally) of the crown's column (an adult's head is about an
eighth of their height; the rest is neck, which the rig leaves still)."""

_NOT_FACE = re.compile(r"hair|hat\b|hat_|helmet|glasses|cap\b", re.IGNORECASE)
_HEAD_NAME = re.compile(r"(?:^|[^a-z0-9])head$", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class AvatarRig:
    """What ``auto_rig_avatar`` returns.

    Attributes:
        avatar: the rigged ``GltfAvatar`` (what was written to ``out``).
        head_node: the head bone's node index (None when the avatar was rigged whole).
        head_meshes: the names of the meshes that got morph targets.
        vertices_rigged: how many vertices the face rig moves (over those meshes).
        names: the morph targets written.
        seconds: wall time per step and in total.
        out: the file written.
        checks: the rigger's checks of the face rig (``check_rig`` under random sparse poses
            of its shapes), None when not asked for.
    """

    avatar: GltfAvatar
    head_node: int | None
    head_meshes: tuple[str, ...]
    vertices_rigged: int
    names: tuple[str, ...]
    seconds: dict
    out: Path
    checks: RigCheck | None = None


def _read_avatar(path: Path) -> GltfAvatar:
    suffix = path.suffix.lower()
    if suffix not in AVATAR_FORMATS:
        raise ValueError(f"avatar: expected one of {AVATAR_FORMATS}, got {path.name}")
    if suffix == ".fbx":
        scene = load_fbx_scene(path)
        if not scene.meshes:
            raise ValueError(f"avatar: {path} holds no mesh")
        avatar = avatar_from_fbx(scene)
        return dataclasses.replace(avatar, path=path)
    avatar = read_gltf_avatar(path)
    extensions = avatar.document.get("extensions", {})
    if "VRM" in extensions:
        raise ValueError(
            f"avatar: {path} is a VRM 0.x file; only VRM 1.0 (VRMC_vrm) is read: convert it "
            "to VRM 1.0 first (e.g. UniVRM or the VRM Add-on for Blender)"
        )
    return avatar


def find_head_node(avatar: GltfAvatar) -> int | None:
    """The head bone's node index (module docstring); None when the avatar has none.
    ValueError when two unrelated nodes are named like a head."""
    document = avatar.document
    humanoid = document.get("extensions", {}).get("VRMC_vrm", {}).get("humanoid", {})
    stated = humanoid.get("humanBones", {}).get("head", {}).get("node")
    if stated is not None:
        return int(stated)
    joints = {j for skin in document.get("skins", []) for j in skin.get("joints", [])}
    nodes = document.get("nodes", [])
    in_scene = scene_nodes(document)
    named = [
        i
        for i, n in enumerate(nodes)
        if i in in_scene and _HEAD_NAME.search(n.get("name", "").strip())
    ]
    if len(named) > 1 and joints:
        named = [i for i in named if i in joints] or named
    tops = [i for i in named if not any(i in node_descendants(document, j) - {j} for j in named)]
    if len(tops) > 1:
        listed = [nodes[i].get("name") for i in tops]
        raise ValueError(
            f"avatar: {len(tops)} unrelated nodes are named like a head ({listed}); "
            "the avatar must hold one head"
        )
    return tops[0] if tops else None


def _face_selection(avatar: GltfAvatar, head: int | None):
    """[(MeshVertices, (V,) bool: the face's vertices)] of the meshes that take targets."""
    document = avatar.document
    below = node_descendants(document, head) if head is not None else None
    layouts = mesh_vertices(avatar)
    top = _head_of_body(layouts) if head is None else None
    chosen = []
    for vertices in layouts:
        name = document["meshes"][vertices.mesh].get("name", "") or document["nodes"][
            vertices.node
        ].get("name", "")
        if _NOT_FACE.search(name) or len(vertices.faces) == 0:
            continue
        if top is not None:
            mask = _without_cut_slivers(top(vertices.world * METRES_TO_CM), vertices.faces)
        elif below is None:
            mask = np.ones(len(vertices.world), bool)
        elif vertices.joints is not None:
            on_head = np.isin(vertices.joints, sorted(below))
            total = np.maximum(vertices.weights.sum(axis=1), 1e-12)
            mask = (vertices.weights * on_head).sum(axis=1) / total > HEAD_WEIGHT
        else:
            mask = np.full(len(vertices.world), vertices.node in below)
        in_faces = np.zeros(len(mask), bool)
        in_faces[vertices.faces[mask[vertices.faces].all(axis=1)].reshape(-1)] = True
        if in_faces.any():
            chosen.append((vertices, in_faces))
    return chosen


def _head_of_body(layouts) -> Callable[[np.ndarray], np.ndarray] | None:
    """For a standing body (``BODY_HEIGHT_CM`` tall along +y): (N, 3) cm -> (N,) bool, the
    points of its head (``HEAD_OF_BODY``); None for anything else."""
    if not layouts:
        return None
    world = np.concatenate([v.world for v in layouts]) * METRES_TO_CM
    extent = np.ptp(world, axis=0)
    height = float(extent[1])
    if not (BODY_HEIGHT_CM[0] <= height <= BODY_HEIGHT_CM[1] and height >= extent.max()):
        return None
    top = float(world[:, 1].max())
    crown = world[world[:, 1] > top - 0.03 * height][:, [0, 2]].mean(axis=0)
    depth, radius = HEAD_OF_BODY

    def inside(points: np.ndarray) -> np.ndarray:
        across = np.linalg.norm(points[:, [0, 2]] - crown, axis=1)
        return (points[:, 1] > top - depth * height) & (across < radius * height)

    return inside


def _without_cut_slivers(mask: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``mask`` less the small pieces the geometric crop cut off something else (a strand
    of hair, a collar's edge): connected pieces under 2 % of the crop that the crop cut
    (a triangle of theirs lies partly outside). Whole parts (eyes, teeth) are kept."""
    from ..mesh import connected_components

    inside = faces[mask[faces].all(axis=1)]
    labels = connected_components(inside, len(mask))
    cut = np.zeros(len(mask), bool)
    cut[faces[mask[faces].any(axis=1) & ~mask[faces].all(axis=1)].ravel()] = True
    out = mask.copy()
    for label in np.unique(labels[inside[:, 0]]) if len(inside) else ():
        piece = (labels == label) & mask
        if piece.sum() < 0.02 * mask.sum() and (piece & cut).any():
            out[piece] = False
    return out


def _what_was_found(source: GltfAvatar, head: int | None, chosen, mesh_names) -> str:
    """The progress line naming the head, the face meshes and (of several) the scene rigged."""
    document = source.document
    head_name = document["nodes"][head].get("name") if head is not None else None
    found = f"the head bone {head_name!r}" if head is not None else "no head bone: rigged whole"
    if head is None and standing_body(source):
        found = "no head bone: the head of a standing body, by geometry"
    count = sum(int(m.sum()) for _, m in chosen)
    line = f"{found}; face meshes {list(mesh_names)}: {count} vertices"
    if len(document.get("scenes", [])) > 1:
        line += (
            f"; the file has {len(document['scenes'])} scenes: its default scene (scene "
            f"{int(document.get('scene', 0))}) is rigged, meshes only in the others are kept "
            "as they are"
        )
    return line


def standing_body(avatar: GltfAvatar) -> bool:
    """Whether the avatar is a standing body whose head ``auto_rig_avatar`` finds by
    geometry when it has no head bone (``BODY_HEIGHT_CM``)."""
    return _head_of_body(mesh_vertices(avatar)) is not None


def _check_face(path: Path, chosen, head: int | None) -> None:
    if not chosen:
        raise ValueError(f"avatar: {path}: no mesh vertices are held by the head bone")
    total = sum(int(mask.sum()) for _, mask in chosen)
    if total > MAX_FACE_VERTICES:
        raise ValueError(
            f"avatar: {path}: the face meshes hold {total} vertices, over the limit of "
            f"{MAX_FACE_VERTICES}; decimate the head (or hide meshes) and try again"
        )
    world = np.concatenate([v.world[m] for v, m in chosen]) * METRES_TO_CM
    size = float((world.max(axis=0) - world.min(axis=0)).max())
    low, high = HEAD_PLAUSIBLE_CM
    if not low <= size <= high:
        found = "no head bone (a node named Head)" if head is None else "a head bone"
        raise ValueError(
            f"avatar: {path}: found {found} and {size:.1f} cm of face geometry (a head is "
            f"{low:g}-{high:g} cm, the file read as metres): give the skeleton a head bone, "
            "or pass a head-only file"
        )


def auto_rig_avatar(
    avatar: str | os.PathLike,
    out: str | os.PathLike,
    *,
    method: AbstractAutoRigMethod | None = None,
    replace: bool = False,
    extras: Sequence[str] = (),
    check: bool = True,
    strict: bool = False,
    progress: Callable[[str], None] | None = None,
    **options,
) -> AvatarRig:
    """Rig a whole avatar's face and write the same avatar with morph targets to ``out``.

    Args:
        avatar: a ``.glb``, ``.vrm`` (1.0) or ``.fbx`` avatar (glTF in metres).
        out: the ``.glb`` to write (atomically; an existing file is replaced only on success),
            or a ``.vrm``: the same with VRM 1.0 expressions (``rig.add_vrm_expressions``;
            the avatar needs a humanoid skeleton).
        method: ``auto_rig``'s method (an ``AbstractAutoRigMethod``; default: its default).
        replace: a target name a face mesh already has is replaced (else a ValueError).
        extras: sets of ``rig.EXTRA_SHAPES`` to add after the rig's shapes (``"visemes"``,
            ``"rpm"``), each target the documented sum of ARKit targets.
        check: run the rigger's checks (``check_rig``) on the face rig before writing.
        strict: a face rig that fails a hard check is not written (a ValueError naming the
            checks); else it is written and the failures are in ``AvatarRig.checks``.
        progress: called with a message before each step.
        options: passed on to ``auto_rig`` (``dataset``, ``up``, ``forward``...).

    Returns an ``AvatarRig``. The blendshapes become targets named as ``auto_rig`` names them
    (ARKit by default); its correctives have no linear equivalent and are not written.
    Raises ValueError naming ``avatar`` for a file it cannot rig (no head, two heads, a VRM
    0.x file, more than ``MAX_FACE_VERTICES`` face vertices), before any compiled work.
    """
    from .._io import check_output_path

    start = time.perf_counter()
    if not isinstance(avatar, str | os.PathLike):
        raise TypeError(f"avatar: expected a file path, got {type(avatar).__name__}")
    path = Path(avatar)
    if not path.is_file():
        raise FileNotFoundError(f"avatar: {path} not found")
    check_output_path(out, "out")
    extras = check_extra_sets(extras)
    say = progress or (lambda message: None)
    source = _read_avatar(path)
    as_vrm = Path(out).suffix.lower() == ".vrm"
    if as_vrm:
        check_humanoid(source.document)
    head = find_head_node(source)
    chosen = _face_selection(source, head)
    _check_face(path, chosen, head)
    document = source.document
    mesh_names = tuple(document["meshes"][v.mesh].get("name", f"mesh{v.mesh}") for v, _ in chosen)
    say(_what_was_found(source, head, chosen, mesh_names))
    seconds = {"read": time.perf_counter() - start}
    parts, faces, offset = [], [], 0
    for vertices, mask in chosen:
        index = np.full(len(mask), -1, np.int64)
        index[mask] = offset + np.arange(int(mask.sum()))
        parts.append(vertices.world[mask] * METRES_TO_CM)
        kept = vertices.faces[mask[vertices.faces].all(axis=1)]
        faces.append(index[kept])
        offset += int(mask.sum())
    neutral, triangles = np.concatenate(parts), np.concatenate(faces).astype(np.int32)
    if not replace:  # a name clash is found before any compiled work
        _check_clashes(path, document, chosen, options, extras)
    result = auto_rig(neutral.astype(np.float32), triangles, method=method, progress=say, **options)
    seconds["rig"] = time.perf_counter() - start - seconds["read"]
    report = _checked(result, path, strict, say) if check or strict else None
    rig = with_extra_shapes(result.rig, extras) if extras else result.rig
    deltas_cm = np.asarray(rig.deltas, np.float64)
    per_mesh = _per_mesh_offsets(chosen, deltas_cm)
    written = {"canrig": {"method": result.method, "correctives_not_written": _n_correctives(rig)}}
    rigged = add_morph_targets(source, per_mesh, rig.names, replace=replace, extras=written)
    if as_vrm:
        rigged = add_vrm_expressions(rigged, sorted(per_mesh), name=path.stem)
    write_gltf_avatar(rigged, out)
    seconds["total"] = time.perf_counter() - start
    say(f"wrote {out}: {rig.n_blendshapes} morph targets on {len(chosen)} meshes")
    moved = np.linalg.norm(deltas_cm, axis=-1).max(axis=0) > 1e-6
    return AvatarRig(
        avatar=rigged,
        head_node=head,
        head_meshes=mesh_names,
        vertices_rigged=int(moved.sum()),
        names=tuple(rig.names),
        seconds=seconds,
        out=Path(out),
        checks=report,
    )


def _checked(result, path: Path, strict: bool, say) -> RigCheck:
    """The rigger's checks of the face rig; with ``strict`` a failed hard check is a
    ValueError (nothing written)."""
    say("checking the face rig (blink, jaw, eyes, teeth, flips, crossings)")
    report = check_auto_rig(result)
    say(report.summary())
    if strict and not report.ok:
        raise ValueError(
            f"avatar: {path}: the face rig fails hard checks: {failed_hard_checks(report)}; "
            "not written"
        )
    return report


def _check_clashes(path, document, chosen, options, extras) -> None:
    expected = _expected_names(options) | {n for s in extras for n in EXTRA_SHAPES[s]}
    for vertices, _ in chosen:
        clash = set(target_names(document, vertices.mesh)) & expected
        if clash:
            raise ValueError(
                f"avatar: {path}: mesh {document['meshes'][vertices.mesh].get('name')!r} "
                f"already has targets named {sorted(clash)[:5]}: pass replace=True "
                "(canrig autorig --replace) to replace them"
            )


def _per_mesh_offsets(chosen, deltas_cm: np.ndarray) -> dict[int, np.ndarray]:
    """{mesh: (K, V, 3) offsets in the mesh's frame and units} of the rig's (K, N, 3) world
    offsets in cm over the chosen vertices (zero elsewhere)."""
    per_mesh, offset = {}, 0
    for vertices, mask in chosen:
        n = int(mask.sum())
        world = np.zeros((len(deltas_cm), len(mask), 3))
        world[:, mask] = deltas_cm[:, offset : offset + n] / METRES_TO_CM
        inverse = np.linalg.inv(vertices.to_world[mask])  # world -> the mesh's frame
        world[:, mask] = np.einsum("vij,kvj->kvi", inverse, world[:, mask])
        per_mesh[vertices.mesh] = world
        offset += n
    return per_mesh


def _n_correctives(rig) -> int:
    return int(sum(int(c.indices.shape[0]) for c in rig.correctives))


def _expected_names(options: dict) -> set[str]:
    """The target names ``auto_rig`` writes under ``options`` (ARKit unless "source")."""
    from ..data import ARKIT_NAMES

    return set(ARKIT_NAMES) if options.get("names", "arkit") == "arkit" else set()
