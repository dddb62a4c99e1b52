"""The MakeHuman hm08 head as a quartic rig: its 52 person-made ARKit targets with
correctives synthesised by ``synthesize_correctives``. Evaluation only: nothing is fitted to
it."""

import os

import numpy as np

from ..data import data_file
from ..mesh import triangulate_quads
from ._blendshape import BlendshapeRig
from ._synthesis import synthesize_correctives


def makehuman_quartic_rig(data_dir: str | os.PathLike | None = None) -> tuple[BlendshapeRig, dict]:
    """The MakeHuman hm08 head (decimetres) with its 52 person-made ARKit targets (visemes
    left out) and correctives synthesised by ``synthesize_correctives`` (default options, in
    cm, converted to the rig's unit).

    Returns the rig and ``{"kept": ..., "seconds": ...}`` from the synthesis report.
    """
    with np.load(data_file("makehuman/hm08_face.npz", data_dir), allow_pickle=False) as z:
        names = [str(n) for n in z["names"]]
        arkit = [i for i, n in enumerate(names) if not n.startswith("viseme_")]
        linear = BlendshapeRig(
            z["neutral"],
            z["deltas"][arkit],
            (),
            [names[i] for i in arkit],
            triangulate_quads(z["polys"]),
            units="dm",
        )
    rig, report = synthesize_correctives(linear, progress=False)
    return rig, {"kept": report.kept, "seconds": report.seconds}
