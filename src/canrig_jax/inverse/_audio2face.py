"""An NVIDIA Audio2Face-3D blendshape-solver configuration as a ``Constrained`` method.

Audio2Face-3D (MIT) ships one JSON file per solve (``bs_skin_config.json``,
``bs_tongue_config.json``) whose ``blendshape_params`` its documentation lists as:

- ``strengthL1regularization``, ``strengthL2regularization``, ``strengthTemporalSmoothing``,
  ``strengthSymmetry``: the weights of the L1, L2, previous-frame and symmetry terms;
- ``numPoses``: the number of blendshapes (without the neutral);
- ``bsSolveActivePoses``: per pose, 1 active or 0 inactive;
- ``bsSolveCancelPoses``, ``bsSolveSymmetryPoses``: per pose an id, poses with the same
  non-negative id form a mutually exclusive (cancel) or a symmetric pair, -1 unpaired;
- ``bsWeightMultipliers``, ``bsWeightOffsets``: per pose a gain and a bias applied to the
  solved weights;
- ``templateBBSize``: the vertical bounding-box height of the template's neutral, in cm.

``from_audio2face_config`` maps each onto ``Constrained``'s fields (the mapping is in its
docstring); fields it does not map (``tolerance``, anything else) are named in a warning.
"""

import json
import os
from typing import Any

import numpy as np

from .._warnings import warn
from ..data import arkit_name_of
from ..rig import BlendshapeRig
from ._base import AbstractInverseMethod
from ._constraints import Constrained
from ._problem import InverseProblem
from ._projected_newton import QuarticNewton

STRENGTHS = {
    "strengthL1regularization": "alpha",
    "strengthL2regularization": "l2_weight",
    "strengthTemporalSmoothing": "temporal_weight",
    "strengthSymmetry": "tie_weight",
}
"""Audio2Face-3D strength field -> the ``Constrained`` (or wrapped method) field it sets."""

PER_POSE = (
    "bsSolveActivePoses",
    "bsSolveCancelPoses",
    "bsSolveSymmetryPoses",
    "bsWeightMultipliers",
    "bsWeightOffsets",
)
"""The per-pose arrays of the configuration, each of length ``numPoses``."""

MAPPED = frozenset({*STRENGTHS, *PER_POSE, "numPoses", "templateBBSize"})


def _read(path: str | os.PathLike) -> dict[str, Any]:
    try:
        with open(path, encoding="utf-8") as file:
            document = json.load(file)
    except OSError as error:
        raise ValueError(f"path: cannot read {path!s}: {error.strerror}") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"path: {path!s} is not JSON ({error.msg}, line {error.lineno})") from None
    if not isinstance(document, dict):
        raise ValueError(f"path: expected a JSON object in {path!s}")
    params = document.get("blendshape_params", document)
    if not isinstance(params, dict):
        raise ValueError("blendshape_params: expected an object of solver settings")
    others = (
        sorted(k for k in document if k != "blendshape_params") if params is not document else []
    )
    unmapped = sorted(k for k in params if k not in MAPPED) + others
    if unmapped:
        warn(f"from_audio2face_config: fields not mapped onto the solver, ignored: {unmapped}")
    missing = sorted(k for k in (*STRENGTHS, *PER_POSE, "numPoses") if k not in params)
    if missing:
        raise ValueError(f"blendshape_params: missing fields {missing} in {path!s}")
    return params


def _pairs(ids: np.ndarray, field: str, rows: np.ndarray) -> list[tuple[int, int]]:
    """Rig index pairs of the poses sharing each non-negative id of ``field``."""
    pairs = []
    for value in sorted(set(ids[ids >= 0].tolist())):
        members = np.flatnonzero(ids == value)
        if len(members) != 2:
            raise ValueError(
                f"{field}: id {value} is shared by {len(members)} poses {members.tolist()}; "
                "an id names a pair (two poses)"
            )
        if (rows[members] >= 0).all():  # poses the rig lacks were checked to be inactive
            pairs.append((int(rows[members[0]]), int(rows[members[1]])))
    return pairs


def _rows(names: tuple[str, ...], pose_names: Any, n_poses: int, active: np.ndarray) -> np.ndarray:
    """(numPoses,) the rig index of each configuration pose (-1: not in the rig)."""
    k = len(names)
    if pose_names is None:
        if n_poses != k:
            raise ValueError(
                f"numPoses: the configuration is of another rig ({n_poses} poses, the rig has "
                f"{k} blendshapes); pass pose_names to map its poses by name"
            )
        return np.arange(k)
    if isinstance(pose_names, str) or len(pose_names) != n_poses:
        raise ValueError(f"pose_names: expected the configuration's {n_poses} pose names in order")
    exact = {n: i for i, n in enumerate(names)}
    canonical = {arkit_name_of(n): i for i, n in enumerate(names) if arkit_name_of(n)}
    rows = np.array(
        [exact.get(p, canonical.get(arkit_name_of(p) or "", -1)) for p in pose_names], np.int64
    )
    lacking = [p for p, r, a in zip(pose_names, rows, active, strict=True) if r < 0 and a]
    if lacking:
        raise ValueError(f"pose_names: active poses the rig does not have: {lacking}")
    taken = rows[rows >= 0]
    if len(set(taken.tolist())) != len(taken):
        raise ValueError("pose_names: two poses map to the same blendshape of the rig")
    return rows


def from_audio2face_config(
    path: str | os.PathLike,
    rig: BlendshapeRig | InverseProblem,
    *,
    pose_names: tuple[str, ...] | list[str] | None = None,
    method: AbstractInverseMethod | None = None,
    strength_scale: float | None = None,
) -> Constrained:
    """A ``Constrained`` method from an Audio2Face-3D blendshape-solver JSON (its
    ``blendshape_params``; see the module docstring for the fields).

    Mapping: ``strengthL1regularization`` -> ``alpha`` of the wrapped method,
    ``strengthL2regularization`` -> ``l2_weight``, ``strengthTemporalSmoothing`` ->
    ``temporal_weight`` (in effect in a warm-started ``Stream``), ``strengthSymmetry`` ->
    ``tie_weight`` over the ``bsSolveSymmetryPoses`` pairs, ``bsSolveCancelPoses`` pairs ->
    ``exclusive``, ``bsSolveActivePoses`` -> ``active``, ``bsWeightMultipliers`` /
    ``bsWeightOffsets`` -> ``multipliers`` / ``offsets``. Each strength is multiplied by
    ``strength_scale``, by default (h / ``templateBBSize``)^2 with h the vertical extent of
    the rig's neutral in rig units: a strength is read as a weight in squared centimetres of
    the template, carried to a head of another size and unit (Audio2Face's own internal
    normalisation of the terms is not documented and not reproduced: tune with
    ``strength_scale``).

    Args:
        path: the JSON file.
        rig: the rig (or its prepared problem) the weights are solved for.
        pose_names: the configuration's pose names in order (Audio2Face keeps them beside the
            shapes, ``bs_skin.npz``'s ``poseNames`` without the neutral), matched to the
            rig's names exactly or by ARKit name (``eyeBlinkLeft`` = ``eyeBlink_L``); rig
            shapes the configuration does not name are inactive (a warning names them).
            None: the poses are the rig's blendshapes in order (``numPoses`` must be K).
        method: the wrapped method (default ``QuarticNewton()``); its ``alpha`` is replaced.
        strength_scale: overrides the default scale of the strengths (> 0).

    Raises a ValueError naming the field for a configuration of another rig (``numPoses``),
    per-pose arrays of the wrong length, an id shared by other than two poses, or poses the
    rig lacks; warns naming the fields it does not map.
    """
    problem_rig = rig.rig if isinstance(rig, InverseProblem) else rig
    if not isinstance(problem_rig, BlendshapeRig):
        raise TypeError(
            f"rig: expected a BlendshapeRig or InverseProblem, got {type(rig).__name__}"
        )
    names = problem_rig.names or tuple(f"shape{i}" for i in range(problem_rig.n_blendshapes))
    params = _read(path)
    n_poses, arrays, strengths = _values(params)
    active_poses = arrays["bsSolveActivePoses"] != 0
    rows = _rows(names, pose_names, n_poses, active_poses)
    scale = _strength_scale(problem_rig, params, strength_scale)
    k = len(names)
    active = np.zeros(k, bool)
    multipliers, offsets = np.ones(k, np.float32), np.zeros(k, np.float32)
    inside = rows >= 0
    active[rows[inside]] = active_poses[inside]
    multipliers[rows[inside]] = arrays["bsWeightMultipliers"][inside]
    offsets[rows[inside]] = arrays["bsWeightOffsets"][inside]
    if pose_names is not None:
        unnamed = sorted(set(range(k)) - set(rows[inside].tolist()))
        if unnamed:
            warn(
                "from_audio2face_config: rig shapes the configuration does not name are "
                f"held inactive: {[names[i] for i in unnamed]}"
            )
    ids = {f: arrays[f].astype(np.int64) for f in ("bsSolveCancelPoses", "bsSolveSymmetryPoses")}
    exclusive = _pairs(ids["bsSolveCancelPoses"], "bsSolveCancelPoses", rows)
    ties = _pairs(ids["bsSolveSymmetryPoses"], "bsSolveSymmetryPoses", rows)
    wrapped = QuarticNewton() if method is None else method
    if not isinstance(wrapped, QuarticNewton):
        raise TypeError(f"method: expected a QuarticNewton to wrap, got {type(wrapped).__name__}")
    wrapped = QuarticNewton(
        alpha=strengths["strengthL1regularization"] * scale,
        iterations=wrapped.iterations,
        tol=wrapped.tol,
        line_steps=wrapped.line_steps,
        upper=wrapped.upper,
        refresh=wrapped.refresh,
    )
    return Constrained(
        wrapped,
        exclusive=tuple(exclusive),
        ties=tuple(ties),
        tie_weight=strengths["strengthSymmetry"] * scale,
        l2_weight=strengths["strengthL2regularization"] * scale,
        temporal_weight=strengths["strengthTemporalSmoothing"] * scale,
        active=active,
        multipliers=multipliers,
        offsets=offsets,
    )


def _values(params: dict[str, Any]) -> tuple[int, dict[str, np.ndarray], dict[str, float]]:
    """(numPoses, the per-pose arrays, the strengths), each checked."""
    n_poses = params["numPoses"]
    if isinstance(n_poses, bool) or not isinstance(n_poses, int) or n_poses < 1:
        raise ValueError(f"numPoses: expected a positive integer, got {n_poses!r}")
    arrays = {}
    for field in PER_POSE:
        try:
            values = np.asarray(params[field], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{field}: expected {n_poses} numbers (numPoses)") from None
        if values.shape != (n_poses,) or not np.isfinite(values).all():
            raise ValueError(
                f"{field}: expected {n_poses} finite values (numPoses), got shape {values.shape}"
            )
        arrays[field] = values
    strengths = {}
    for field in STRENGTHS:
        value = params[field]
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value < np.inf:
            raise ValueError(f"{field}: expected a non-negative number, got {value!r}")
        strengths[field] = float(value)
    return n_poses, arrays, strengths


def _strength_scale(rig: BlendshapeRig, params: dict[str, Any], override: float | None) -> float:
    if override is not None:
        if isinstance(override, bool) or not (
            isinstance(override, int | float) and 0 < override < np.inf
        ):
            raise ValueError(f"strength_scale: expected a positive number, got {override!r}")
        return float(override)
    size = params.get("templateBBSize")
    if size is None:
        raise ValueError("templateBBSize: missing; pass strength_scale to scale the strengths")
    if isinstance(size, bool) or not isinstance(size, int | float) or not 0 < size < np.inf:
        raise ValueError(f"templateBBSize: expected a positive height in cm, got {size!r}")
    neutral = np.asarray(rig.neutral, np.float64)
    height = float(neutral[:, 1].max() - neutral[:, 1].min())
    return (height / float(size)) ** 2
