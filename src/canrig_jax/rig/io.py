"""Save and load a ``BlendshapeRig`` as one .npz (written atomically)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..io import save_npz
from .blendshape import BlendshapeRig, Corrective


def save_rig(path: str | os.PathLike, rig: BlendshapeRig) -> Path:
    """Write ``rig`` to ``path`` (.npz), atomically."""
    arrays = {
        "neutral": np.asarray(rig.neutral),
        "deltas": np.asarray(rig.deltas),
        "names": np.array(rig.names, dtype=str),
        "orders": np.array([c.order for c in rig.correctives], dtype=np.int32),
    }
    if rig.faces is not None:
        arrays["faces"] = np.asarray(rig.faces)
    for c in rig.correctives:
        arrays[f"order{c.order}_indices"] = np.asarray(c.indices)
        arrays[f"order{c.order}_vertices"] = np.asarray(c.vertices)
        arrays[f"order{c.order}_deltas"] = np.asarray(c.deltas)
    return save_npz(path, **arrays)


def load_rig(path: str | os.PathLike) -> BlendshapeRig:
    """Read a rig written by ``save_rig``."""
    with np.load(path, allow_pickle=False) as z:
        correctives = tuple(
            Corrective(z[f"order{n}_indices"], z[f"order{n}_vertices"], z[f"order{n}_deltas"])
            for n in z["orders"]
        )
        return BlendshapeRig(
            z["neutral"],
            z["deltas"],
            correctives,
            tuple(str(n) for n in z["names"]),
            z["faces"] if "faces" in z.files else None,
        )
