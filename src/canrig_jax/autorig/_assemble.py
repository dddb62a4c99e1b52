"""The rig of a head from the poses a method generated: correctives from the combination
poses, ARKit names, the example shapes taken as sculpted (one step of ``auto_rig``)."""

from collections.abc import Mapping

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from .._warnings import warn
from ..data import arkit_name_of
from ..rig import UNIT_IN_CM, BlendshapeRig, rename_to_arkit
from ._data import PoseSet
from ._rig import rig_from_poses


def assemble(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    displacements: Float[ArrayLike, "P V 3"],
    styled: Float[ArrayLike, "P V 3"] | None,
    pose_set: PoseSet | None,
    source_names: tuple[str, ...],
    names: str,
    sculpted: Mapping[str, Float[np.ndarray, "V 3"]],
) -> tuple[BlendshapeRig, tuple[str, ...]]:
    """The rig in the head's own frame (cm) and the ARKit names of the example shapes taken as
    sculpted.

    Args:
        vertices: (V, 3) the head's neutral (cm); faces: (F, 3).
        displacements: (P, V, 3) the method's poses in the head's frame (cm); styled: the
            same with the examples' ``Style`` applied (None without examples). A styled rig
            keeps the unstyled blinks: the blink's amplitude is the lid's own
            (``close_blinks``), not the style's.
        pose_set: the method's combination poses (None: a linear rig of ``source_names``).
        names: "arkit" (``rename_to_arkit``) or "source".
        sculpted: {ARKit name: (V, 3) cm}, the artist's shapes put in the rig as given.
    """
    poses = (displacements,) if styled is None else (styled, displacements)
    rigs = [_rig(vertices, faces, d, pose_set, source_names, names) for d in poses]
    rig = rigs[0] if styled is None else _with_blinks_of(*rigs)
    return _take_sculpted(rig, sculpted)


def _rig(vertices, faces, displacements, pose_set, source_names, names) -> BlendshapeRig:
    """The rig in the head's own frame from its (P, V, 3) displacements (cm): correctives
    from the combination poses of ``pose_set`` (None: a linear rig of ``source_names``)."""
    neutral = np.asarray(vertices, np.float32)
    displacements = np.asarray(displacements, np.float32)
    if pose_set is not None:
        rig = rig_from_poses(neutral, faces, displacements, pose_set)
    else:
        rig = BlendshapeRig(neutral, displacements, (), source_names, faces)
    return rename_to_arkit(rig) if names == "arkit" else rig


def _with_blinks_of(rig: BlendshapeRig, other: BlendshapeRig) -> BlendshapeRig:
    """``rig`` with ``other``'s eyeBlink shapes (same names and mesh)."""
    deltas = np.array(rig.deltas)
    for i, name in enumerate(rig.names):
        if arkit_name_of(str(name)) in ("eyeBlinkLeft", "eyeBlinkRight"):
            deltas[i] = np.asarray(other.deltas[i])
    return BlendshapeRig(rig.neutral, deltas, rig.correctives, rig.names, rig.faces, rig.units)


def _take_sculpted(rig: BlendshapeRig, sculpted: Mapping):
    """The rig with each example shape replaced by the artist's, matched by ARKit name, and
    the ARKit names replaced; a channel the rig splits into halves (ICT's
    ``browInnerUp_L``/``_R``) or lacks keeps the generated shape, with a warning."""
    if not sculpted:
        return rig, ()
    deltas = np.array(rig.deltas, np.float32)
    scale = 1.0 / UNIT_IN_CM[rig.units]
    channels = [arkit_name_of(str(name)) for name in rig.names]
    taken = []
    for i, arkit in enumerate(channels):
        if arkit in sculpted and channels.count(arkit) == 1:
            deltas[i] = np.asarray(sculpted[arkit], np.float32) * scale
            taken.append(arkit)
    left = [n for n in sculpted if n not in taken]
    if left:
        warn(
            f"examples: {', '.join(left)} shaped the style but are not in the rig as given "
            "(no such shape in the method's rig, or a channel it splits into halves)"
        )
    rig = BlendshapeRig(rig.neutral, deltas, rig.correctives, rig.names, rig.faces, rig.units)
    return rig, tuple(n for n in sculpted if n in taken)
