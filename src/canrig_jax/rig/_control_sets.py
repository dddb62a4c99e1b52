"""Control sets: the groups of blend shapes one mesh carries side by side, and a rig cut down to
one of them.

Avatar libraries ship one head with several sets of controls over the same neutral: Microsoft
Rocketbox's facial FBX files hold 175 blend shapes in one list, told apart by a numbered prefix:

- ``arkit``: the 52 ARKit shapes (``AK_25_JawOpen``; any spelling ``data.arkit_name_of``
  recognises: ``jawOpen``, ``JawOpen``, ``jawOpen_L``...);
- ``facs``: FACS action units (``AU_26_JawDrop``, ``AU_12_L_LipCornerPuller``; also ``AU12``);
- ``sranipal``: the VIVE SRanipal eye and lip shapes (``SR_21_Jaw_Open``);
- ``visemes``: the speech visemes (``AA_VI_10_aa``).

Other names (Rocketbox's ``HB_`` extras, ``_Neutral``) belong to no set. A namespace or a
blend-shape node prefix (``head:``, ``blendShape1.``) is ignored.
"""

import re
from collections.abc import Sequence

import numpy as np

from ..data import arkit_name_of
from ._blendshape import BlendshapeRig, Corrective

CONTROL_SETS: tuple[str, ...] = ("arkit", "facs", "sranipal", "visemes")
"""The control sets ``control_set_of`` tells apart (see the module docstring)."""

_PREFIXES = {
    "facs": re.compile(r"AU_?\d+(_|$)", re.IGNORECASE),
    "sranipal": re.compile(r"SR_\d+_", re.IGNORECASE),
    "visemes": re.compile(r"AA_VI_\d+_", re.IGNORECASE),
}
"""The numbered prefix of each set's shape names, other than ARKit's (``arkit_name_of``)."""


def control_set_of(name: str) -> str | None:
    """The control set (one of ``CONTROL_SETS``) a blend-shape name belongs to, or None.

    ``AK_25_JawOpen`` and ``jawOpen`` give ``"arkit"``, ``AU_26_JawDrop`` ``"facs"``,
    ``SR_21_Jaw_Open`` ``"sranipal"``, ``AA_VI_10_aa`` ``"visemes"``, ``HB_08_TongueOut`` None.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a string, got {type(name).__name__}")
    if arkit_name_of(name) is not None:
        return "arkit"
    bare = name.rsplit(":", 1)[-1].rsplit(".", 1)[-1]
    return next((s for s, prefix in _PREFIXES.items() if prefix.match(bare)), None)


def select_blendshapes(rig: BlendshapeRig, names: Sequence[str]) -> BlendshapeRig:
    """The rig with only the blendshapes ``names``, in that order (same neutral, faces, units).

    A corrective is kept when every one of its drivers is kept (re-indexed), and dropped
    otherwise: the kept shapes then give the same meshes as in ``rig`` with the dropped
    shapes at weight 0.

    Raises ValueError naming ``names`` for a string (not a sequence), an empty selection, a
    repeated name or a name the rig lacks (all of them listed).
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if isinstance(names, str):
        raise ValueError(f"names: expected a sequence of names, got the string {names!r}")
    names = [str(n) for n in names]
    if not names:
        raise ValueError("names: expected at least one blendshape name")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"names: repeated blendshape names {repeated}")
    lookup = {n: i for i, n in enumerate(rig.names)}
    unknown = [n for n in names if n not in lookup]
    if unknown:
        raise ValueError(
            f"names: the rig has no blendshapes {unknown} (it has {rig.n_blendshapes}: "
            f"{list(rig.names[:8])}...)"
        )
    keep = np.array([lookup[n] for n in names], np.int64)
    new_index = np.full(rig.n_blendshapes, -1, np.int64)
    new_index[keep] = np.arange(keep.size)
    tables = []
    for table in rig.correctives:
        indices = np.asarray(table.indices)
        rows = np.flatnonzero(np.all(new_index[indices] >= 0, axis=1))
        if rows.size:
            tables.append(
                Corrective(
                    new_index[indices[rows]].astype(np.int32),
                    table.vertices,
                    np.asarray(table.deltas)[rows],
                )
            )
    return BlendshapeRig(
        rig.neutral,
        np.asarray(rig.deltas)[keep],
        tuple(tables),
        tuple(names),
        rig.faces,
        rig.units,
    )


def select_control_set(rig: BlendshapeRig, control_set: str) -> BlendshapeRig:
    """The rig's blendshapes of one control set (``CONTROL_SETS``), in the rig's order, with
    the correctives among them (``select_blendshapes``).

    Load every shape of a file first, e.g. ``load_fbx_rig(path, names="all", crop="head")``
    for a Rocketbox head; its ARKit shapes then carry ARKit names (``jawOpen``), the others
    their names in the file (``SR_21_Jaw_Open``).

    Raises ValueError naming ``control_set`` for an unknown set, or a rig with no shape of it
    (listing the sets it has).
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if control_set not in CONTROL_SETS:
        raise ValueError(f"control_set: expected one of {CONTROL_SETS}, got {control_set!r}")
    sets = [control_set_of(n) for n in rig.names]
    names = [n for n, s in zip(rig.names, sets, strict=True) if s == control_set]
    if not names:
        present = sorted({s for s in sets if s is not None})
        raise ValueError(
            f"control_set: the rig has no {control_set!r} shape (its {rig.n_blendshapes} "
            f"shapes hold the sets {present}; names {list(rig.names[:5])}...)"
        )
    return select_blendshapes(rig, names)
