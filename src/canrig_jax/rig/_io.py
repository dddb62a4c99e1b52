"""Save and load a ``BlendshapeRig`` as one .npz (written atomically)."""

import os
from pathlib import Path

import numpy as np

from .._io import CorruptFileError, check_output_path, save_npz
from ..data import read_arrays
from ._blendshape import BlendshapeRig, Corrective


def save_rig(path: str | os.PathLike, rig: BlendshapeRig) -> Path:
    """Write ``rig`` to ``path`` (.npz), atomically."""
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    check_output_path(path)
    arrays = {
        "neutral": np.asarray(rig.neutral),
        "deltas": np.asarray(rig.deltas),
        "names": np.array(rig.names, dtype=str),
        "orders": np.array([c.order for c in rig.correctives], dtype=np.int32),
        "units": np.array(rig.units, dtype=str),
    }
    if rig.faces is not None:
        arrays["faces"] = np.asarray(rig.faces)
    for c in rig.correctives:
        arrays[f"order{c.order}_indices"] = np.asarray(c.indices)
        arrays[f"order{c.order}_vertices"] = np.asarray(c.vertices)
        arrays[f"order{c.order}_deltas"] = np.asarray(c.deltas)
    return save_npz(path, **arrays)


def load_rig(path: str | os.PathLike) -> BlendshapeRig:
    """Read a rig written by ``save_rig`` (its ``units`` too; "cm" for a file written before
    rigs had units); a damaged file raises ``CorruptFileError`` (a
    ValueError) naming it, a missing one FileNotFoundError."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"path: rig file {path} not found")
    orders = read_arrays(path, ("orders",))["orders"]
    keys = ["neutral", "deltas", "names"]
    for n in orders:
        keys += [f"order{n}_indices", f"order{n}_vertices", f"order{n}_deltas"]
    with np.load(path, allow_pickle=False) as z:
        has_faces, has_units = "faces" in z.files, "units" in z.files
    optional = (["faces"] if has_faces else []) + (["units"] if has_units else [])
    z = read_arrays(path, keys + optional)
    try:
        correctives = tuple(
            Corrective(z[f"order{n}_indices"], z[f"order{n}_vertices"], z[f"order{n}_deltas"])
            for n in orders
        )
        return BlendshapeRig(
            z["neutral"],
            z["deltas"],
            correctives,
            tuple(str(n) for n in z["names"]),
            z["faces"] if has_faces else None,
            str(z["units"]) if has_units else "cm",  # files from before ``units``: ICT's cm
        )
    except (ValueError, TypeError) as error:
        raise CorruptFileError(f"{path}: corrupt rig file ({error})") from error
