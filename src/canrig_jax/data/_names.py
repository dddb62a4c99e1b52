"""ARKit blendshape names across conventions, and retargeting weights between rigs by name.

Three spellings of the same 52 ARKit channels meet in the data:

- ARKit camelCase (``eyeBlinkLeft``), Apple's ``ARFaceAnchor.BlendShapeLocation``;
- Unreal's ``EARFaceBlendShape`` / Live Link Face (``EyeBlinkLeft``);
- ICT Face Model (``eyeBlink_L``), which splits ``browInnerUp`` and ``cheekPuff`` into
  ``_L``/``_R`` halves and has no ``tongueOut``.

``to_arkit`` maps any of them to the ARKit spelling; ``retarget_weights`` moves a weight
array from one rig's channel list onto another's through that canonical name.
"""

import dataclasses
import re
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float, Float32

from .._checks import check_real
from .._warnings import warn

ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft",
    "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)  # fmt: skip
"""The 52 ARKit blendshapes in Apple's documented order (Unreal's EARFaceBlendShape order)."""

ICT_SPLIT = ("browInnerUp", "cheekPuff")
"""ARKit channels that ICT splits into ``_L``/``_R`` halves."""


def _spellings(arkit: str) -> list[str]:
    """All accepted spellings of one ARKit channel (ARKit, Unreal, ICT)."""
    out = [arkit, arkit[0].upper() + arkit[1:]]
    for side, suffix in (("Left", "_L"), ("Right", "_R")):
        if arkit.endswith(side):
            out.append(arkit[: -len(side)] + suffix)
    if arkit in ICT_SPLIT:
        out += [arkit + "_L", arkit + "_R"]
    return out


_TO_ARKIT = {spelling: a for a in ARKIT_NAMES for spelling in _spellings(a)}


def _canonical(names: Sequence[str], argument: str) -> list[str]:
    """ARKit names of ``names``; a ValueError naming ``argument`` lists every unknown one."""
    if isinstance(names, str):
        raise ValueError(f"{argument}: expected a sequence of names, got the string {names!r}")
    arkit = [arkit_name_of(n) if isinstance(n, str) else None for n in names]
    unknown = [n for n, a in zip(names, arkit, strict=True) if a is None]
    if unknown:
        raise ValueError(
            f"{argument}: not ARKit blendshape names (ARKit 'eyeBlinkLeft', Unreal "
            f"'EyeBlinkLeft', ICT 'eyeBlink_L' or numbered 'AK_09_EyeBlinkLeft' spelling "
            f"expected): {unknown}"
        )
    return [a for a in arkit if a is not None]  # all of them (no name is unknown)


_NUMBERED = re.compile(r"AK_\d+_", re.IGNORECASE)
"""The numbered prefix of ARKit shapes in some exported rigs (Rocketbox: ``AK_25_JawOpen``)."""


def arkit_name_of(name: str) -> str | None:
    """ARKit camelCase spelling of a blendshape name from a rig file, or None when it names
    no ARKit shape.

    Accepts what ``to_arkit`` accepts (ARKit ``eyeBlinkLeft``, Unreal ``EyeBlinkLeft``, ICT
    ``eyeBlink_L``) behind an optional Maya namespace or blend-shape node prefix
    (``head:``, ``blendShape1.``) and an optional numbered prefix ``AK_NN_`` (Rocketbox:
    ``AK_01_BrowDownLeft`` gives ``browDownLeft``). A name such as ``AA_VI_00_Sil`` (a
    viseme) gives None.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a string, got {type(name).__name__}")
    bare = name.rsplit(":", 1)[-1].rsplit(".", 1)[-1]
    numbered = _NUMBERED.match(bare)
    if numbered:
        bare = bare[numbered.end() :]
    return _TO_ARKIT.get(bare)


def to_arkit(name: str) -> str:
    """ARKit camelCase spelling of an ARKit, Unreal or ICT blendshape name.

    ``EyeBlinkLeft``, ``eyeBlinkLeft`` and ``eyeBlink_L`` all give ``eyeBlinkLeft``;
    ICT's ``browInnerUp_L``/``_R`` give ``browInnerUp``; the prefixes ``arkit_name_of``
    strips are accepted too (``AK_09_EyeBlinkLeft``). A ValueError for any other name.
    """
    return _canonical([name], "name")[0]


@dataclasses.dataclass(frozen=True)
class RetargetReport:
    """What a name-based retarget could not carry over (``retarget_weights`` lists the
    fields)."""

    unused_source: tuple[str, ...]
    missing_target: tuple[str, ...]
    averaged: tuple[tuple[str, ...], ...]


def retarget_weights(
    weights: Float[ArrayLike, "*frames K"],
    source_names: Sequence[str],
    target_names: Sequence[str],
    missing: str = "raise",
) -> tuple[Float32[np.ndarray, "*frames K_target"], RetargetReport]:
    """Map blendshape weights over ``source_names`` onto ``target_names`` by ARKit name.

    Each target channel takes the source channel with the same canonical ARKit name, so a
    split target (ICT ``browInnerUp_L`` and ``_R``) takes the single source value twice.
    Several source channels with one canonical name (ICT's halves into an ARKit rig) are
    averaged. Source channels the target does not read are listed in the report and named
    in a ``warnings.warn``; they are never dropped silently.

    Args:
        weights: (..., K_source) weights, unitless (ARKit range 0..1), finite.
        source_names: K_source channel names (ARKit, Unreal or ICT spelling).
        target_names: K_target channel names of the receiving rig.
        missing: ``"raise"`` (a target channel with no source is an error) or ``"zero"``
            (such channels get weight 0 and are listed in the report).

    Returns:
        ``(weights_out, report)``: (..., K_target) float32 and a ``RetargetReport`` of what
        could not be carried over: ``unused_source``, the source channels no target channel
        reads (e.g. ``TongueOut`` for ICT); ``missing_target``, the target channels with no
        source (zero-filled when ``missing="zero"``); ``averaged``, the groups of source
        channels averaged into one ARKit channel (e.g. ICT's ``browInnerUp_L``/``_R`` read by
        a rig with a single ``browInnerUp``).
    """
    if missing not in ("raise", "zero"):
        raise ValueError(f"missing: expected 'raise' or 'zero', got {missing!r}")
    weights = np.asarray(weights)
    source = _canonical(source_names, "source_names")
    target = _canonical(target_names, "target_names")
    source_names = [str(n) for n in source_names]
    target_names = [str(n) for n in target_names]
    if weights.ndim < 1 or weights.shape[-1] != len(source):
        raise ValueError(
            f"weights: expected shape (..., {len(source)}) to match source_names, "
            f"got {weights.shape}"
        )
    check_real("weights", weights)
    if not np.all(np.isfinite(weights)):
        raise ValueError("weights: contains non-finite values")

    columns: dict[str, list[int]] = {}
    for i, name in enumerate(source):
        columns.setdefault(name, []).append(i)
    missing_target = tuple(t for t, c in zip(target_names, target, strict=True) if c not in columns)
    if missing_target and missing == "raise":
        raise ValueError(
            f"target_names: no source channel for {list(missing_target)}; "
            f"pass missing='zero' to fill them with 0"
        )
    # (K_source, K_target) selection matrix; a column averages the sources of one name.
    mixing = np.zeros((len(source), len(target)), dtype=np.float64)
    for j, name in enumerate(target):
        for i in columns.get(name, []):
            mixing[i, j] = 1.0 / len(columns[name])
    out = (weights.astype(np.float64) @ mixing).astype(np.float32)

    used = set(target)
    unused_source = tuple(s for s, c in zip(source_names, source, strict=True) if c not in used)
    averaged = tuple(
        tuple(source_names[i] for i in idx)
        for name, idx in columns.items()
        if len(idx) > 1 and name in used
    )
    if unused_source:
        warn(
            f"retarget_weights: source channels not used by the target: {list(unused_source)}",
        )
    return out, RetargetReport(unused_source, missing_target, averaged)
