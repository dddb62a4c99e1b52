"""The targets apps expect beyond the 52 ARKit shapes, as fixed combinations of them.

TalkingHead and Ready Player Me consumers read the 15 Oculus visemes (``viseme_sil`` ...
``viseme_U``) and five RPM extras (``mouthOpen``, ``mouthSmile``, ``eyesClosed``,
``eyesLookUp``, ``eyesLookDown``). ``EXTRA_SHAPES`` defines each as a weighted sum of ARKit
shapes (the table in ``docs/guides/avatars.md``), and ``with_extra_shapes`` appends them to a
rig: ``delta_extra = sum_i c_i delta_i``, exactly (float64 sums, stored as float32). A term
whose shape the rig lacks (e.g. ``tongueOut``) is left out, with a warning naming it. The rig's
correctives are not folded into an extra: an extra is a plain linear shape.
"""

from collections.abc import Sequence

import numpy as np

from .._warnings import warn
from ._blendshape import BlendshapeRig

VISEMES: dict[str, dict[str, float]] = {
    "viseme_sil": {},
    "viseme_PP": {"mouthPressLeft": 0.5, "mouthPressRight": 0.5, "mouthRollLower": 0.3,
                  "mouthRollUpper": 0.3},
    "viseme_FF": {"mouthRollLower": 0.6, "mouthUpperUpLeft": 0.3, "mouthUpperUpRight": 0.3,
                  "jawOpen": 0.1},
    "viseme_TH": {"jawOpen": 0.2, "tongueOut": 0.4, "mouthUpperUpLeft": 0.2,
                  "mouthUpperUpRight": 0.2},
    "viseme_DD": {"jawOpen": 0.25, "mouthStretchLeft": 0.2, "mouthStretchRight": 0.2},
    "viseme_kk": {"jawOpen": 0.3, "mouthStretchLeft": 0.3, "mouthStretchRight": 0.3},
    "viseme_CH": {"jawOpen": 0.2, "mouthFunnel": 0.5, "mouthPucker": 0.2},
    "viseme_SS": {"jawOpen": 0.1, "mouthStretchLeft": 0.4, "mouthStretchRight": 0.4,
                  "mouthSmileLeft": 0.2, "mouthSmileRight": 0.2},
    "viseme_nn": {"jawOpen": 0.2, "mouthStretchLeft": 0.2, "mouthStretchRight": 0.2,
                  "mouthClose": 0.1},
    "viseme_RR": {"jawOpen": 0.2, "mouthFunnel": 0.3, "mouthPucker": 0.3},
    "viseme_aa": {"jawOpen": 0.7, "mouthLowerDownLeft": 0.3, "mouthLowerDownRight": 0.3},
    "viseme_E": {"jawOpen": 0.35, "mouthStretchLeft": 0.4, "mouthStretchRight": 0.4,
                 "mouthSmileLeft": 0.2, "mouthSmileRight": 0.2},
    "viseme_I": {"jawOpen": 0.25, "mouthSmileLeft": 0.5, "mouthSmileRight": 0.5,
                 "mouthStretchLeft": 0.2, "mouthStretchRight": 0.2},
    "viseme_O": {"jawOpen": 0.45, "mouthFunnel": 0.6, "mouthPucker": 0.3},
    "viseme_U": {"jawOpen": 0.2, "mouthPucker": 0.8, "mouthFunnel": 0.3},
}  # fmt: skip
"""The 15 Oculus visemes as weighted sums of ARKit shapes (``viseme_sil`` is the rest face)."""

RPM_EXTRAS: dict[str, dict[str, float]] = {
    "mouthOpen": {"jawOpen": 1.0},
    "mouthSmile": {"mouthSmileLeft": 1.0, "mouthSmileRight": 1.0},
    "eyesClosed": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "eyesLookUp": {"eyeLookUpLeft": 1.0, "eyeLookUpRight": 1.0},
    "eyesLookDown": {"eyeLookDownLeft": 1.0, "eyeLookDownRight": 1.0},
}
"""Ready Player Me's five extra targets as sums of ARKit shapes."""

EXTRA_SHAPES: dict[str, dict[str, dict[str, float]]] = {"visemes": VISEMES, "rpm": RPM_EXTRAS}
"""The extra sets by name (``canrig autorig --extras visemes,rpm``)."""


def check_extra_sets(sets: Sequence[str]) -> tuple[str, ...]:
    """``sets`` as a tuple of known set names; ValueError naming ``extras`` otherwise."""
    if isinstance(sets, str):
        sets = [s.strip() for s in sets.split(",") if s.strip()]
    unknown = [s for s in sets if s not in EXTRA_SHAPES]
    if unknown:
        raise ValueError(f"extras: unknown sets {unknown}; expected some of {list(EXTRA_SHAPES)}")
    return tuple(dict.fromkeys(sets))


def with_extra_shapes(
    rig: BlendshapeRig, sets: Sequence[str] = ("visemes", "rpm")
) -> BlendshapeRig:
    """``rig`` with the shapes of ``sets`` (``EXTRA_SHAPES``) appended after its own, each the
    weighted sum of the rig's ARKit shapes its table gives (module docstring).

    Raises ValueError naming ``extras`` for an unknown set, and naming ``rig`` when an extra's
    name is already one of the rig's or the rig has none of an extra's shapes (but for
    ``viseme_sil``, which is the rest face)."""
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    sets = check_extra_sets(sets)
    table = {name: terms for s in sets for name, terms in EXTRA_SHAPES[s].items()}
    clash = [n for n in table if n in rig.names]
    if clash:
        raise ValueError(f"rig: already has shapes named {clash}")
    column = {n: i for i, n in enumerate(rig.names)}
    deltas = np.asarray(rig.deltas, np.float64)
    extra, lacking = [], set()
    for name, terms in table.items():
        present = {k: c for k, c in terms.items() if k in column}
        lacking |= set(terms) - set(present)
        if terms and not present:
            raise ValueError(f"rig: has none of {name}'s shapes {sorted(terms)}")
        total = np.zeros(deltas.shape[1:])
        for shape, weight in present.items():
            total += weight * deltas[column[shape]]
        extra.append(total)
    if lacking:
        warn(f"with_extra_shapes: the rig has no {sorted(lacking)}; those terms are left out")
    stacked = np.concatenate([deltas, np.asarray(extra).reshape(-1, *deltas.shape[1:])])
    return BlendshapeRig(
        rig.neutral,
        stacked.astype(np.float32),
        rig.correctives,
        (*rig.names, *table),
        rig.faces,
        units=rig.units,
    )
