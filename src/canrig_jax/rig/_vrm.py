"""VRM 1.0 expressions (``VRMC_vrm``) bound to an avatar's ARKit morph targets.

VRM apps read a face through ``VRMC_vrm.expressions``: 18 presets (``happy`` ... ``neutral``)
and any custom ones, each a list of ``morphTargetBinds`` (a node with a mesh, a target index
of that mesh, a weight 0..1). ``add_vrm_expressions`` binds each preset to the ARKit
combination of ``VRM_PRESETS`` (the table in ``docs/guides/avatars.md``) and writes every ARKit
target as a custom expression of its own name ("perfect sync"); none of the ARKit names is a
preset's. A file that already has ``VRMC_vrm`` keeps its meta and humanoid; another avatar gets
a humanoid found from its bone names (``humanoid_bones``: Mixamo, Rocketbox / 3ds Max Biped,
and plain names such as ``LeftUpperArm``) and a meta that names it.
"""

import json
import re

from ._gltf_avatar import GltfAvatar, target_names

VRM_PRESETS: dict[str, dict[str, float]] = {
    "happy": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8, "cheekSquintLeft": 0.4,
              "cheekSquintRight": 0.4},
    "angry": {"browDownLeft": 1.0, "browDownRight": 1.0, "mouthFrownLeft": 0.5,
              "mouthFrownRight": 0.5, "noseSneerLeft": 0.4, "noseSneerRight": 0.4},
    "sad": {"browInnerUp": 1.0, "mouthFrownLeft": 0.7, "mouthFrownRight": 0.7},
    "relaxed": {"mouthSmileLeft": 0.4, "mouthSmileRight": 0.4, "eyeSquintLeft": 0.3,
                "eyeSquintRight": 0.3},
    "surprised": {"browInnerUp": 0.8, "browOuterUpLeft": 0.8, "browOuterUpRight": 0.8,
                  "eyeWideLeft": 0.6, "eyeWideRight": 0.6, "jawOpen": 0.4},
    "aa": {"jawOpen": 0.8},
    "ih": {"jawOpen": 0.2, "mouthSmileLeft": 0.5, "mouthSmileRight": 0.5},
    "ou": {"jawOpen": 0.1, "mouthPucker": 0.9},
    "ee": {"jawOpen": 0.3, "mouthStretchLeft": 0.6, "mouthStretchRight": 0.6},
    "oh": {"jawOpen": 0.4, "mouthFunnel": 0.7},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "blinkLeft": {"eyeBlinkLeft": 1.0},
    "blinkRight": {"eyeBlinkRight": 1.0},
    "lookUp": {"eyeLookUpLeft": 1.0, "eyeLookUpRight": 1.0},
    "lookDown": {"eyeLookDownLeft": 1.0, "eyeLookDownRight": 1.0},
    "lookLeft": {"eyeLookOutLeft": 1.0, "eyeLookInRight": 1.0},
    "lookRight": {"eyeLookInLeft": 1.0, "eyeLookOutRight": 1.0},
    "neutral": {},
}  # fmt: skip
"""The VRM 1.0 preset expressions as ARKit combinations (``neutral`` binds nothing)."""

REQUIRED_BONES = (
    "hips", "spine", "head",
    "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm", "rightLowerArm", "rightHand",
    "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg", "rightFoot",
)  # fmt: skip
"""The humanoid bones VRM 1.0 requires."""

_BONE_NAMES = {  # VRM bone: name tails (lower case, after a prefix), in order of preference
    "hips": ("hips", "pelvis"),
    "spine": ("spine",),
    "chest": ("chest", "spine1"),
    "neck": ("neck",),
    "head": ("head",),
    "leftUpperArm": ("leftarm", "leftupperarm", "l upperarm"),
    "leftLowerArm": ("leftforearm", "leftlowerarm", "l forearm"),
    "leftHand": ("lefthand", "l hand"),
    "rightUpperArm": ("rightarm", "rightupperarm", "r upperarm"),
    "rightLowerArm": ("rightforearm", "rightlowerarm", "r forearm"),
    "rightHand": ("righthand", "r hand"),
    "leftUpperLeg": ("leftupleg", "leftupperleg", "l thigh"),
    "leftLowerLeg": ("leftleg", "leftlowerleg", "l calf"),
    "leftFoot": ("leftfoot", "l foot"),
    "rightUpperLeg": ("rightupleg", "rightupperleg", "r thigh"),
    "rightLowerLeg": ("rightleg", "rightlowerleg", "r calf"),
    "rightFoot": ("rightfoot", "r foot"),
}
_PREFIX = re.compile(r"^(mixamorig\d*:|bip0?1 |j_bip_[clr]_)", re.IGNORECASE)


def humanoid_bones(document: dict) -> dict[str, int]:
    """{VRM bone: node index} found from the nodes' names (module docstring); the file's own
    ``VRMC_vrm`` humanoid when it has one. Bones not found are absent."""
    stated = document.get("extensions", {}).get("VRMC_vrm", {}).get("humanoid", {})
    if stated.get("humanBones"):
        return {k: int(v["node"]) for k, v in stated["humanBones"].items()}
    by_name: dict[str, int] = {}
    for i, node in enumerate(document.get("nodes", [])):
        name = _PREFIX.sub("", node.get("name", "").strip()).lower().replace("_", "")
        by_name.setdefault(name, i)
    found = {}
    for bone, tails in _BONE_NAMES.items():
        for tail in tails:
            if tail in by_name:
                found[bone] = by_name[tail]
                break
    return found


def check_humanoid(document: dict) -> dict[str, int]:
    """``humanoid_bones(document)``; ValueError naming ``avatar`` when a bone VRM requires is
    not found."""
    bones = humanoid_bones(document)
    missing = [b for b in REQUIRED_BONES if b not in bones]
    if missing:
        raise ValueError(
            f"avatar: a VRM needs a humanoid skeleton; no bone found for {missing} (write a "
            ".glb instead, or name the bones as Mixamo or VRM do)"
        )
    return bones


def add_vrm_expressions(
    avatar: GltfAvatar, meshes: list[int], *, name: str = "avatar"
) -> GltfAvatar:
    """``avatar`` with ``VRMC_vrm`` 1.0: presets bound by ``VRM_PRESETS`` and each ARKit target
    of ``meshes`` (mesh indices, by ``extras.targetNames``) as a custom expression.

    Raises ValueError naming ``avatar`` when the skeleton lacks a bone VRM requires."""
    from ..data import ARKIT_NAMES

    document = json.loads(json.dumps(avatar.document))
    bones = check_humanoid(document)
    hosts = {}  # mesh -> the node that shows it
    for i, node in enumerate(document.get("nodes", [])):
        if node.get("mesh") in meshes:
            hosts.setdefault(node["mesh"], i)
    names = {m: target_names(document, m) for m in meshes}

    def binds(terms: dict[str, float]) -> list[dict]:
        out = []
        for m in meshes:
            for shape, weight in terms.items():
                if shape in names[m] and m in hosts:
                    index = names[m].index(shape)
                    out.append({"node": hosts[m], "index": index, "weight": float(weight)})
        return out

    def expression(terms, binary=False) -> dict:
        return {"morphTargetBinds": binds(terms), "isBinary": binary}

    preset = {p: expression(terms) for p, terms in VRM_PRESETS.items()}
    present = [n for n in ARKIT_NAMES if any(n in names[m] for m in meshes)]
    custom = {n: expression({n: 1.0}) for n in present}
    vrm = document.setdefault("extensions", {}).get("VRMC_vrm") or {
        "specVersion": "1.0",
        "meta": {
            "name": name,
            "version": "1",
            "authors": ["unknown (rigged by canrig_jax)"],
            "licenseUrl": "https://vrm.dev/licenses/1.0/",
        },
        "humanoid": {"humanBones": {b: {"node": n} for b, n in bones.items()}},
    }
    vrm["expressions"] = {"preset": preset, "custom": custom}
    document["extensions"]["VRMC_vrm"] = vrm
    used = document.setdefault("extensionsUsed", [])
    if "VRMC_vrm" not in used:
        used.append("VRMC_vrm")
    return GltfAvatar(document, avatar.blob, avatar.path)
