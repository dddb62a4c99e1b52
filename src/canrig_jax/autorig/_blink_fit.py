"""The blink's amplitude from the head's own measurement: the eyeBlink shapes scaled until
the lid covers the eyeball (a shape carried from another head, or predicted, often stops
short of a lid gap of another size: a Rocketbox eye stays 36-45 % open under ICT's blink).

Measured as ``check_rig``'s ``blink_closes`` measures it: the share of the eyeball's open
front that a ray cast forward still reaches past the lids."""

from collections.abc import Collection

import numpy as np

from ..data import arkit_name_of
from ..mesh import self_intersections
from ..rig import UNIT_IN_CM, BlendshapeRig
from ._rig_checks import _entered, _head, _movers, _visible

GAINS = tuple(np.round(np.arange(1.0, 2.51, 0.1), 2))
"""The gains tried, smallest first."""

CLOSED = 0.05
"""The share of the open eye left visible that counts as closed."""


def close_blinks(
    rig: BlendshapeRig,
    *,
    up: str = "+y",
    forward: str = "+z",
    keep: Collection[str] = (),
) -> tuple[BlendshapeRig, dict[str, float]]:
    """Scale each eyeBlink shape by the smallest of ``GAINS`` that closes its eye (at most
    ``CLOSED`` of the open front left visible) without pushing more than a tenth more of the
    lid's moving vertices into the eyeball or passing the lid through the other one (at most
    half a new skin crossing per moving lid vertex more than at gain 1); where none closes
    it, the allowed gain that covers the most. Shapes named in ``keep`` (an artist's
    examples, ARKit or rig names) and rigs without separate eyeballs are left as they are.
    ``auto_rig`` calls it on the unstyled blink (the lid's own amplitude, not a style's).

    Returns the rig and {shape name: gain} of the shapes looked at (1.0: unchanged)."""
    if rig.faces is None:
        return rig, {}
    head = _head(rig, up, forward)
    if not head.eyes:
        return rig, {}
    scale = UNIT_IN_CM[rig.units]
    deltas = np.array(rig.deltas)
    gains = {}
    visible_open = [_visible(head, head.neutral, e) for e in range(len(head.eyes))]
    for k, name in enumerate(rig.names):
        arkit = arkit_name_of(str(name))
        if arkit not in ("eyeBlinkLeft", "eyeBlinkRight") or arkit in keep or name in keep:
            continue
        delta = deltas[k].astype(np.float64) * scale
        lid = _movers(delta, head.skin, 0.25)
        if len(lid) == 0:
            continue
        shares = np.array(
            [[_visible(head, head.neutral + g * delta, e) / max(visible_open[e], 1e-9)
              for e in range(len(head.eyes))] for g in GAINS]
        )  # fmt: skip
        eye = int(np.argmin(shares[0]))
        entered = np.array(
            [_entered(head, head.neutral[lid], head.neutral[lid] + g * delta[lid], eye).mean()
             for g in GAINS]
        )  # fmt: skip
        frames = head.neutral + np.asarray(GAINS)[:, None, None] * delta
        crossings = self_intersections(frames, head.neutral, head.faces, mask=head.skin_faces)
        allowed = (entered <= entered[0] + 0.1) & (crossings <= crossings[0] + len(lid) // 2)
        closes = np.flatnonzero(allowed & (shares[:, eye] <= CLOSED))
        best = closes[0] if len(closes) else int(np.argmin(np.where(allowed, shares[:, eye], 2)))
        gains[str(name)] = float(GAINS[best])
        deltas[k] *= GAINS[best]
    changed = BlendshapeRig(rig.neutral, deltas, rig.correctives, rig.names, rig.faces, rig.units)
    return changed, gains
