"""Protocols of the PBS experiments that are more than orchestration: the check that a saved
PBS model matches the run that resumes or evaluates it, and Table 6's reach floor
(``experiments/canrig_pbs.py`` calls these; the tests call them here)."""

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from ..._metrics import CM_TO_MM
from ...pbs._basis import PatchLayout


def check_pbs_training_matches(
    folder: str | Path,
    *,
    handles_on: str,
    graph: str,
    attach: Sequence[str] = (),
    attach_onto: Sequence[str] = (),
) -> None:
    """Refuse (``ValueError`` naming the flag) to resume or evaluate the PBS model saved in
    ``folder`` with other options than it was trained with: another ``handles_on``, or, for a
    masked model, another ``graph`` (and, on the ``"attached"`` graph, other ``attach`` /
    ``attach_onto`` part names). ``folder/train.json`` says how it was trained (before these
    options existed: ``"skin"`` and ``"mesh"``); without it there is nothing to check. A
    folder named ``shape_transformer*`` holds the Shape Transformer, which has no masks, so
    only ``handles_on`` is checked."""
    folder = Path(folder)
    meta = folder / "train.json"
    if not meta.exists():
        return
    meta = json.loads(meta.read_text())
    run = {"handles_on": handles_on, "graph": graph, "attach": attach, "attach_onto": attach_onto}
    trained = {"handles_on": meta.get("handles_on", "skin")}
    if not folder.name.startswith("shape_transformer"):  # the Shape Transformer has no masks
        trained["graph"] = meta.get("graph", "mesh")
        if trained["graph"] == "attached" and graph == "attached":
            trained["attach"] = meta["attach"]
            trained["attach_onto"] = meta["attach_onto"]
    for name, value in trained.items():
        if name in ("attach", "attach_onto"):
            same = list(value) == list(run[name])
        else:
            same = value == run[name]
        if not same:
            flag = "--" + name.replace("_", "-")
            raise ValueError(
                f"{flag}: {folder} was trained with {flag} {value}, this run uses {run[name]}"
            )


def reach_floor(
    layout: PatchLayout,
    patch_distance_cm: Float[ArrayLike, "P N"],
    handles: Int[ArrayLike, " H"],
    source: Float[ArrayLike, "T N 3"],
    target: Float[ArrayLike, "T N 3"],
    region: Bool[ArrayLike, " N"],
    *,
    reach_cm: float,
) -> tuple[float, int]:
    """Lower bound of a patch-blendshape edit's mean error over ``region`` (Table 6's mouth
    difference), whatever the network: a vertex of ``region`` whose every covering patch is
    seeded farther than ``reach_cm`` (the clamped mask's reach) from every moved handle keeps
    the ``source`` frame, so its error ``|source - target|`` is unavoidable.

    ``patch_distance_cm`` (P, N): geodesic distance in cm from each patch's seed to each
    vertex; ``handles`` (H,): the moved handle vertices; ``source``, ``target`` (T, N, 3) in
    cm; ``region`` (N,). Returns ``(floor_mm, n_unreached)``: the unreached vertices' error
    summed and divided by the number of ``region`` vertices (mm, averaged over the T frames),
    and how many region vertices are unreached."""
    distances = np.asarray(patch_distance_cm)
    region = np.asarray(region, bool)
    handles = np.asarray(handles)
    if distances.ndim != 2 or distances.shape[0] != layout.n_patches:
        raise ValueError(
            f"patch_distance_cm: expected shape ({layout.n_patches}, N), got {distances.shape}"
        )
    if region.shape != distances.shape[1:] or not region.any():
        raise ValueError(f"region: expected a non-empty ({distances.shape[1]},) mask")
    if np.shape(source) != np.shape(target) or np.shape(source)[1:] != (region.size, 3):
        raise ValueError(
            f"source, target: expected the same (T, {region.size}, 3) shape, got "
            f"{np.shape(source)} and {np.shape(target)}"
        )
    if handles.size == 0:
        raise ValueError("handles: expected at least one handle")
    if not reach_cm > 0:
        raise ValueError(f"reach_cm: expected > 0, got {reach_cm}")
    reached_patch = distances[:, handles].min(axis=1) <= reach_cm  # (P,)
    unreached = region & ~layout.covered_by(reached_patch)
    error = np.linalg.norm(np.asarray(source) - np.asarray(target), axis=-1) * CM_TO_MM
    return float(error[:, unreached].sum(axis=1).mean() / region.sum()), int(unreached.sum())
