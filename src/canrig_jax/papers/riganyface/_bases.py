"""The deformation-transfer bases of the auto-rigging evaluation and each evaluated row's rig
on a head: plain and anchored transfer of every pose (kept on disk between runs for the
training heads), and the rigs of a set of models, each on its base.

Displacements are (P, V, 3) centimetres, P the poses of ``dataset.poses``.
"""

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float

from ..._io import atomic_path
from ...autorig._data import AutorigDataset, PoseSet, RiggedHead, transfer_poses
from ...autorig._makehuman import MakeHumanHead
from ...autorig._methods import ANCHOR_CM
from ...autorig._model import RigAnyFace
from ...autorig._rig import GeneratedRig, generate_rig
from ...mesh import MeshOperators, TriangleCorrespondence


def cached_transfer(
    dataset: AutorigDataset,
    head: RiggedHead,
    cache: str | Path | None,
    seed: int,
    static_below: float | None = None,
    *,
    anchor: str = "vertex",
) -> Float[np.ndarray, "P V 3"]:
    """``transfer_poses(dataset, head, static_below=, anchor=)`` as float32 (cm), kept in the
    folder ``cache`` when it is given (``None``: always computed).

    The file is named by the kind of transfer (plain, or anchored below ``static_below`` cm per
    ``anchor``), ``seed`` (the training set's) and ``head.name``; a stored array is used only
    if its shape is ``head.displacements``' (P, V, 3), else it is recomputed and replaced
    (written atomically)."""
    path = None
    if cache is not None:
        kind = "dt" if static_below is None else f"dt_anchored{static_below:g}"
        kind += "" if static_below is None or anchor == "vertex" else f"_{anchor}"
        path = Path(cache) / f"{kind}_seed{seed}_{head.name.replace('/', '_')}.npy"
        if path.exists():
            stored = np.load(path, allow_pickle=False)
            if stored.shape == head.displacements.shape:
                return stored
    transferred = transfer_poses(dataset, head, static_below=static_below, anchor=anchor)
    transferred = transferred.astype(np.float32)
    if path is not None:
        with atomic_path(path) as tmp, open(tmp, "wb") as file:
            np.save(file, transferred, allow_pickle=False)
    return transferred


def anchored_base_key(mode: str) -> str:
    """Key of the deformation-transfer base anchored per ``mode`` (``transfer_poses(anchor=)``)
    in ``transfer_bases``' result, and its rows' suffix without the leading '_': "anchored"
    for "vertex", "anchored_<mode>" else."""
    return "anchored" if mode == "vertex" else f"anchored_{mode}"


def transfer_bases(
    dataset: AutorigDataset,
    head: RiggedHead | MakeHumanHead,
    correspondence: TriangleCorrespondence | None = None,
    plain: Float[np.ndarray, "P V 3"] | None = None,
    anchors: Sequence[str] = ("vertex",),
) -> dict[str, Float[np.ndarray, "P V 3"]]:
    """The residual models' bases on ``head`` (cm): ``"plain"``, deformation transfer of every
    pose (``plain`` when already computed), and the transfer anchored below
    ``ANCHOR_CM`` per each mode of ``anchors``, under ``anchored_base_key(mode)``."""
    if plain is None:
        plain = transfer_poses(dataset, head, correspondence)
    bases = {"plain": plain}
    for mode in anchors:
        bases[anchored_base_key(mode)] = transfer_poses(
            dataset, head, correspondence, static_below=ANCHOR_CM, anchor=mode
        )
    return bases


def generate_rows(
    models: Mapping[str, RigAnyFace],
    rows: Mapping[str, tuple[str, str | None]],
    poses: PoseSet,
    head: RiggedHead | MakeHumanHead,
    bases: Mapping[str, Float[ArrayLike, "P V 3"]],
    operators: MeshOperators | None = None,
    placement: tuple[Float[ArrayLike, " 3"], float] | None = None,
) -> dict[str, GeneratedRig]:
    """Each evaluation row's rig generated on ``head`` (``head.vertices`` (V, 3) cm,
    ``head.faces``): ``rows`` maps a row name to (a name in ``models``, the key of its base in
    ``bases`` or None for a model without one); ``operators`` and ``placement`` are
    ``generate_rig``'s (default: computed, and the head's bounding box)."""
    return {
        name: generate_rig(
            models[model_name],
            poses,
            head.vertices,
            head.faces,
            operators=operators,
            base=None if base is None else bases[base],
            placement=placement,
        )
        for name, (model_name, base) in rows.items()
    }
