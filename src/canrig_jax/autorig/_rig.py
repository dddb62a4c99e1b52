"""Rig generation: a neutral head in, a ``BlendshapeRig`` out, in one batched call.

``generate_rig`` (reached through the network methods' one door,
``AbstractNetworkMethod.generate``) normalises the head to the unit sphere, computes (or loads)
its operators, predicts every pose of the pose set at once and scales back to the head's
units. Single
expressions become the rig's deltas; a combination pose becomes a corrective of its order,
its prediction minus its expressions' predictions and minus the correctives of its
sub-combinations (Racković eq. (5)), so evaluating the rig with weight 1 on a combination's
expressions reproduces the predicted combination pose.
"""

import dataclasses
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..mesh import MeshOperators, check_mesh, mesh_operators
from ..rig import BlendshapeRig, Corrective
from ._data import PoseSet
from ._model import RigAnyFace, normalise
from ._orientation import CONVENTION, HeadOrientation, head_orientation

ORIENTATIONS = ("check", "fix", "trust")

DEFAULT_MEMORY_BUDGET = 4 * 2**30
"""Bytes of activations ``generate_rig`` may plan for (4 GiB)."""


def activation_bytes(model: RigAnyFace, n_vertices: int, n_poses: int, k: int) -> int:
    """Rough peak activation memory of one forward pass (float32): a few (V, P, width)
    tensors per conditional block plus the dense operators (V, k)."""
    width = int(model.first.out_features)
    per_block = 8 * n_vertices * n_poses * width
    return 4 * (per_block + 4 * n_vertices * k)


DEFAULT_POSE_CHUNK = 16
"""Poses per pass through the conditional blocks in ``generate_rig`` (see ``RigAnyFace``)."""


@eqx.filter_jit
def predict_displacements(
    model: RigAnyFace,
    poses: Float[Array, "P A"],
    vertices: Float[Array, "V 3"],
    operators: MeshOperators,
    pose_chunk: int | None = None,
    base: Float[Array, "P V 3"] | None = None,
) -> Float[Array, "P V 3"]:
    """The jitted forward pass ``model(poses, vertices, operators)``: (P, V, 3) displacements
    of every pose (no validation; ``generate_rig`` is the checked entry point). ``base``:
    a residual model's base displacements (unit-sphere units)."""
    return model(poses, vertices, operators, base=base, pose_chunk=pose_chunk)


@dataclasses.dataclass(frozen=True)
class GeneratedRig:
    """A generated rig with the raw predictions and timings.

    Attributes:
        rig: the ``BlendshapeRig`` (head units, deltas named after the basis expressions,
            correctives for the combination poses).
        displacements: (P, V, 3) predicted displacement of every pose (head units).
        seconds: wall time in total, of the orientation check, the operators, and the
            network.
        orientation: what ``head_orientation`` found (None with ``orientation="trust"``).
        rotated: True when ``orientation="fix"`` turned the head for the model (and the
            predictions back).
    """

    rig: BlendshapeRig
    displacements: Float[np.ndarray, "P V 3"]
    seconds: dict
    orientation: HeadOrientation | None = None
    rotated: bool = False


def pad_to_bucket(operators: MeshOperators, bucket: int) -> MeshOperators:
    """``operators`` padded so every size is a multiple of ``bucket`` (sparse entries: of
    8 ``bucket``)."""
    if bucket < 1:
        raise ValueError(f"bucket: expected >= 1, got {bucket}")
    up = lambda n, b=bucket: -(-int(n) // b) * b  # noqa: E731
    nnz = {
        name: up(getattr(operators, name).values.shape[0], 8 * bucket)
        for name in ("laplacian", "gradient_x", "gradient_y")
    }
    return operators.pad(
        up(operators.n_vertices),
        up(operators.faces.shape[0]),
        int(operators.eigenvalues.shape[0]),
        nnz,
    )


def rig_from_poses(
    neutral: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    displacements: Float[ArrayLike, "P V 3"],
    poses: PoseSet,
) -> BlendshapeRig:
    """A ``BlendshapeRig`` whose poses reproduce ``displacements`` (P, V, 3)."""
    displacements = np.asarray(displacements)
    a = poses.n_basis
    deltas = displacements[:a]
    terms: dict[frozenset, np.ndarray] = {}  # corrective of each combination so far
    order = sorted(range(a, poses.n_poses), key=lambda p: len(poses.combinations[p]))
    for p in order:
        combo = frozenset(poses.combinations[p])
        # the rig at weight 1 on `combo` adds every corrective of a subset of it
        lower = sum((v for s, v in terms.items() if s < combo), np.zeros_like(deltas[0]))
        terms[combo] = displacements[p] - deltas[sorted(combo)].sum(axis=0) - lower
    by_order: dict[int, tuple[list, list]] = {}
    for p in order:
        combo = poses.combinations[p]
        indices, dense = by_order.setdefault(len(combo), ([], []))
        indices.append(combo)
        dense.append(terms[frozenset(combo)])
    correctives = tuple(
        Corrective.from_dense(np.asarray(indices), np.stack(dense))
        for _, (indices, dense) in sorted(by_order.items())
    )
    return BlendshapeRig(neutral, deltas, correctives, poses.basis_names, faces)


def generate_rig(
    model: RigAnyFace,
    poses: PoseSet,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    k: int = 128,
    operators: MeshOperators | None = None,
    cache: str | os.PathLike | bool | None = False,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    bucket: int = 256,
    pose_chunk: int | None = DEFAULT_POSE_CHUNK,
    base: Float[ArrayLike, "P V 3"] | None = None,
    orientation: str = "check",
    placement: tuple[Float[ArrayLike, " 3"], float] | None = None,
) -> GeneratedRig:
    """Build the rig of a neutral head (any triangulation, any number of parts).

    Args:
        model: a trained ``RigAnyFace``; poses: its ``PoseSet``.
        vertices: (V, 3) neutral head in any units (the rig comes back in the same units);
            faces: (F, 3) triangles.
        k: eigenpairs for the operators (the model's training value).
        operators: precomputed operators of the *normalised* head (skips their cost).
        cache: operator disk cache (``False``: compute, a cold start; see ``mesh_operators``).
        memory_budget: refuse heads whose activations would exceed this many bytes.
        bucket: pad vertex, face and operator sizes up to a multiple of this, so heads of
            similar size share one compiled network (padding does not change the result).
        pose_chunk: poses per pass through the network's conditional blocks (``None``: all
            at once); the result does not depend on it, the speed and memory do.
        base: only for a residual model ("DT + learned residual"): (P, V, 3) base
            displacements of every pose in the head's units (``transfer_poses``).
        orientation: the model expects +y up and +z forward (ICT). ``"check"`` (default):
            refuse a head whose shape clearly faces elsewhere (``head_orientation``: mirror
            symmetry, the nose tip, eyes and neck cut; ~15 ms at 1,700 vertices); ``"fix"``:
            turn such a head into the convention for the model and turn the predictions
            back (the rig stays in the head's frame); ``"trust"``: no check. Heads whose
            cues are inconclusive (a sphere, a face-only mask's up direction) pass: this is
            the network's low-level call; ``auto_rig`` (``canrig autorig``) decides the
            orientation from a fit of the face, or refuses, and never lets a head through
            on a guess.
        placement: ``(centre (3,), scale)`` to normalise the head with instead of its
            bounding box (``face_placement``: from a fit of the ICT face, not from where the
            head was cropped); the head's frame, its units.

    Raises ValueError for a head without faces, non-finite or ill-shaped input, a pose set
    that does not match the model, a head too large for ``memory_budget``, or (``"check"``)
    a head that faces elsewhere.
    """
    start = time.perf_counter()
    vertices, faces, base = _check_rig_inputs(
        model, poses, vertices, faces, k, bucket, memory_budget, pose_chunk, base, orientation
    )
    found, rotation = _orientation_for_model(vertices, faces, orientation, operators)
    placement = _check_placement(placement)
    after_orientation = time.perf_counter()
    original = vertices
    if rotation is not None:  # an axis permutation with signs: exact in floating point
        vertices = np.asarray(vertices @ rotation.T)
        if base is not None:
            base = base @ rotation.T
        if placement is not None:
            placement = (rotation @ placement[0], placement[1])
    _check_memory(model, vertices.shape[0], poses.n_poses, pose_chunk, k, memory_budget)
    if placement is None:
        unit, _, scale = normalise(vertices)
    else:
        unit, scale = (vertices - placement[0]) / placement[1], placement[1]
    unit = unit.astype(np.float32)
    if operators is None:
        operators = mesh_operators(unit, faces, k=k, cache=cache)
    elif operators.n_vertices != unit.shape[0]:
        raise ValueError(
            f"operators: built for {operators.n_vertices} vertices, the head has {unit.shape[0]}"
        )
    after_operators = time.perf_counter()
    predicted = _predict_padded(model, poses, unit, operators, bucket, pose_chunk, base, scale)
    if rotation is not None:
        predicted = predicted @ rotation  # back into the head's frame
    after_network = time.perf_counter()
    if not np.all(np.isfinite(predicted)):
        raise ValueError("model: produced non-finite displacements for this head")
    rig = rig_from_poses(original.astype(np.float32), faces, predicted.astype(np.float32), poses)
    end = time.perf_counter()
    return GeneratedRig(
        rig=rig,
        displacements=predicted.astype(np.float32),
        seconds={
            "total": end - start,
            "orientation": after_orientation - start,
            "operators": after_operators - after_orientation,
            "network": after_network - after_operators,
        },
        orientation=found,
        rotated=rotation is not None,
    )


def _check_rig_inputs(
    model, poses, vertices, faces, k, bucket, memory_budget, pose_chunk, base, orientation
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``generate_rig``'s checks: (vertices, faces, base float64 or None)."""
    if not isinstance(model, RigAnyFace):
        raise TypeError(f"model: expected a trained RigAnyFace, got {type(model).__name__}")
    if not isinstance(poses, PoseSet):
        raise TypeError(f"poses: expected the model's PoseSet, got {type(poses).__name__}")
    for name, value in (("k", k), ("bucket", bucket), ("memory_budget", memory_budget)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name}: expected a positive integer, got {value!r}")
    vertices, faces = check_mesh(vertices, faces)
    if poses.n_basis != model.n_pose_inputs:
        raise ValueError(
            f"poses: pose vectors of length {poses.n_basis}, the model takes {model.n_pose_inputs}"
        )
    if pose_chunk is not None and pose_chunk < 1:
        raise ValueError(f"pose_chunk: expected a positive number of poses, got {pose_chunk}")
    if model.residual:
        if base is None:
            raise ValueError(
                "base: this model predicts a correction on top of deformation transfer; pass "
                "the head's transferred poses (P, V, 3) in its units (transfer_poses)"
            )
        base = np.asarray(base, np.float64)
        if base.shape != (poses.n_poses, vertices.shape[0], 3) or not np.all(np.isfinite(base)):
            raise ValueError(
                f"base: expected finite displacements of shape "
                f"({poses.n_poses}, {vertices.shape[0]}, 3), got {base.shape}"
            )
    elif base is not None:
        raise ValueError("base: only a residual model takes base displacements")
    if orientation not in ORIENTATIONS:
        raise ValueError(f"orientation: expected one of {ORIENTATIONS}, got {orientation!r}")
    return vertices, faces, base


def _orientation_for_model(
    vertices: np.ndarray, faces: np.ndarray, orientation: str, operators: MeshOperators | None
) -> tuple[HeadOrientation | None, np.ndarray | None]:
    """(what ``head_orientation`` found or None, the rotation that turns the head into the
    model's convention or None); raises for a head ``orientation`` does not let through."""
    found, rotation = None, None
    if orientation != "trust":
        found = head_orientation(vertices, faces)
        if found.contradicts:
            if orientation == "check":
                raise ValueError(
                    f"vertices: the head seems to face another way than the model's convention "
                    f"({CONVENTION}): {found.describe()}; rotate it, or pass "
                    "orientation='fix' (turn it for the model and back) or 'trust'"
                )
            if not found.determined:
                raise ValueError(
                    f"vertices: the head does not face the model's convention ({CONVENTION}) "
                    f"and its orientation is only partly determined ({found.describe()}); "
                    "orientation='fix' cannot turn it: rotate it yourself"
                )
            rotation = found.rotation
            if operators is not None:
                raise ValueError(
                    "operators: given for the head as stored, but orientation='fix' turns it; "
                    "pass operators=None"
                )
    return found, rotation


def _check_placement(placement):
    """``placement`` as ((3,) float64 centre, float scale), or None."""
    if placement is not None:
        centre, scale = placement
        centre = np.asarray(centre, np.float64)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise ValueError(f"placement: expected a finite (3,) centre, got {centre.shape}")
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"placement: expected a positive scale, got {scale!r}")
        placement = (centre, float(scale))
    return placement


def _check_memory(model, n_vertices: int, n_poses: int, pose_chunk, k: int, memory_budget: int):
    """Refuse a head whose activations would exceed ``memory_budget`` bytes."""
    per_pass = n_poses if pose_chunk is None else min(pose_chunk, n_poses)
    needed = activation_bytes(model, n_vertices, per_pass, k)
    if needed > memory_budget:
        raise ValueError(
            f"vertices: a head of {n_vertices} vertices needs ~{needed / 2**30:.1f} GiB "
            f"for {per_pass} poses per pass, above memory_budget={memory_budget / 2**30:.1f} GiB; "
            "decimate it, lower pose_chunk or raise memory_budget"
        )


def _predict_padded(model, poses, unit, operators, bucket, pose_chunk, base, scale):
    """(P, V, 3) float64 displacements in the head's units: the network on the head and its
    operators padded to ``bucket`` (``base`` in the head's units), cut back to V."""
    padded = pad_to_bucket(operators, bucket)
    unit_padded = np.zeros((padded.n_vertices, 3), np.float32)
    unit_padded[: unit.shape[0]] = unit
    base_padded = None
    if base is not None:
        base_padded = np.zeros((poses.n_poses, padded.n_vertices, 3), np.float32)
        base_padded[:, : unit.shape[0]] = base / scale
        base_padded = jnp.asarray(base_padded)
    predicted = predict_displacements(
        model,
        jnp.asarray(poses.vectors()),
        jnp.asarray(unit_padded),
        padded,
        pose_chunk,
        base_padded,
    )
    predicted = np.asarray(jax.block_until_ready(predicted), np.float64)[:, : unit.shape[0]]
    return predicted * scale
