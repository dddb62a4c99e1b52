"""Layering of edits (Seol et al., section 5.2).

Two edits at nearly the same pose make the RBF system nearly singular: the interpolant passes
through both with huge, opposite coefficients and overshoots around them (overfitting). The
layering rule puts a new edit that lies within ``eta`` (Euclidean distance in weight space) of
an edit already in a layer into the first layer that has none that close, a new one if needed.
Each layer is an independent pose-space edit with its own sigma; layers are fitted in order,
layer n to what the artist sculpted minus the base mesh and layers 0..n-1 at its poses, and
their corrections add. An edit at exactly the pose of an earlier one therefore overrides it
there: the later sculpt wins, which is the tested handling of duplicated poses.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..rig import BlendshapeRig, evaluate_batch
from ._pse import (
    PoseSpaceEdit,
    check_edits,
    check_pose,
    check_sigma,
    correction,
    fit_pose_space_edit,
)


class LayeredEdits(eqx.Module):
    """Independent pose-space edits whose corrections add (``fit_layered`` lists the
    fields)."""

    layers: tuple[PoseSpaceEdit, ...]
    assignment: tuple[int, ...] = eqx.field(static=True)

    @property
    def n_layers(self) -> int:
        return len(self.layers)


def assign_layers(poses: Float[ArrayLike, "P K"], eta: float) -> list[int]:
    """Layer of each edit, in order: the first layer with no edit within ``eta``."""
    poses = np.asarray(poses, np.float64)
    if not np.isfinite(eta) or eta < 0:
        raise ValueError(f"eta: expected a finite value >= 0, got {eta}")
    members: list[list[int]] = []
    assignment = []
    for i, pose in enumerate(poses):
        for layer, edits in enumerate(members):
            if np.all(np.linalg.norm(poses[edits] - pose, axis=1) > eta):
                edits.append(i)
                assignment.append(layer)
                break
        else:
            members.append([i])
            assignment.append(len(members) - 1)
    return assignment


def fit_layered(
    rig: BlendshapeRig,
    poses: Float[ArrayLike, "P K"],
    edits: Float[ArrayLike, "P V 3"],
    *,
    sigma: float,
    eta: float,
    layer_sigma: float | Sequence[float] | None = None,
    **options,
) -> LayeredEdits:
    """Fit edits in layers (the layering rule with threshold ``eta``).

    Args:
        rig, poses, edits: as ``fit_pose_space_edit`` (edits in the order they were made).
        sigma: width of layer 0.
        eta: edits closer than this (Euclidean, weight units) never share a layer.
        layer_sigma: width of layers 1, 2, ... (one value for all, or one per layer; default
            ``sigma``).
        **options: passed to ``fit_pose_space_edit`` (metric, local_frames, ridge, ...).

    Returns:
        A ``LayeredEdits`` for ``apply_layered``: ``layers``, one ``PoseSpaceEdit`` per layer
        in fitting order (``n_layers`` of them), and ``assignment``, the layer of each input
        edit.
    """
    poses, edits = check_edits(rig, poses, edits)
    check_sigma(sigma)
    assignment = assign_layers(poses, eta)
    n_layers = max(assignment) + 1
    if layer_sigma is None:
        widths = [sigma] * n_layers
    elif np.ndim(layer_sigma) == 0:
        widths = [sigma] + [float(np.asarray(layer_sigma))] * (n_layers - 1)
    else:
        widths = [sigma, *[float(s) for s in np.asarray(layer_sigma)]]
        if len(widths) < n_layers:
            raise ValueError(
                f"layer_sigma: expected at least {n_layers - 1} widths, got {len(widths) - 1}"
            )
    for width in widths[:n_layers]:
        check_sigma(width)
    posed = np.asarray(evaluate_batch(rig, poses))
    target = posed + edits  # what the artist sculpted at each pose
    layers: list[PoseSpaceEdit] = []
    assignment_array = np.asarray(assignment)
    for layer in range(n_layers):
        members = np.flatnonzero(assignment_array == layer)
        current = jax.vmap(_add_layers, (None, 0, 0))(
            tuple(layers), jnp.asarray(poses[members]), jnp.asarray(posed[members])
        )
        residual = target[members] - np.asarray(current)
        layers.append(
            fit_pose_space_edit(rig, poses[members], residual, sigma=widths[layer], **options)
        )
    return LayeredEdits(tuple(layers), tuple(assignment))


def apply_layered(
    layered: LayeredEdits, weights: Float[ArrayLike, " K"], posed: Float[ArrayLike, "V 3"]
) -> Float[Array, "V 3"]:
    """The base mesh ``posed`` at ``weights`` plus every layer's correction (each layer's
    frames come from the base mesh)."""
    if not layered.layers:
        return jnp.asarray(posed)
    check_pose(layered.layers[0], weights, posed)
    return _add_layers(layered.layers, jnp.asarray(weights, jnp.float32), jnp.asarray(posed))


def _add_layers(layers, weights, posed):
    mesh = posed
    for layer in layers:
        mesh = mesh.at[layer.vertices].add(correction(layer, weights, posed))
    return mesh
