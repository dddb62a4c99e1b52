"""Animated glTF 2.0: a rig's morph targets driven over time by a take's weights.

The file holds the rig as ``export_gltf`` writes it (one morph target per blendshape and per
corrective term) plus one animation whose ``weights`` channel sets every target's weight at
every frame. A corrective target's weight is the product of its drivers' weights (Racković
eq. (5)), computed per frame and written as a key, so at each key the glTF mesh equals
``evaluate(rig, w)`` exactly; between keys players interpolate linearly. An optional head
rotation (yaw, pitch, roll in radians) animates a parent node that pivots about the head's
bounding-box centre.
"""

import os
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float, Float32

from .._checks import check_finite, check_real
from ._blendshape import BlendshapeRig, combination_coefficients
from ._gltf import _ARRAY_BUFFER, _FLOAT, _check_rig, _rig_document, _write_glb


def morph_target_weights(
    rig: BlendshapeRig, weights: Float[ArrayLike, "T K"]
) -> Float32[np.ndarray, "T KC"]:
    """(T, K + C) glTF morph weights of (T, K) rig weights: the K blendshape weights then,
    for each corrective term (in ``export_gltf``'s target order), the product of its drivers'
    weights."""
    weights = np.asarray(weights, np.float64)
    columns = [weights]
    for table in rig.correctives:  # the rig's own product, on (K, T) columns of weights
        product = combination_coefficients(weights.T, np.asarray(table.indices))
        columns.append(np.asarray(product).T)
    return np.concatenate(columns, axis=1).astype(np.float32)


def head_rotation_quaternions(
    yaw_pitch_roll: Float[ArrayLike, "T 3"],
) -> Float32[np.ndarray, "T 4"]:
    """(T, 4) unit quaternions (x, y, z, w; glTF order) of (T, 3) yaw, pitch, roll in radians:
    yaw about +Y (up), pitch about +X, roll about +Z, applied roll first (R = Ry Rx Rz)."""
    angles = np.asarray(yaw_pitch_roll, np.float64)
    half = angles / 2
    cy, sy = np.cos(half[:, 0]), np.sin(half[:, 0])
    cp, sp = np.cos(half[:, 1]), np.sin(half[:, 1])
    cr, sr = np.cos(half[:, 2]), np.sin(half[:, 2])
    zero = np.zeros_like(cy)

    def product(a, b):  # Hamilton product of (x, y, z, w) quaternions
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return (
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        )

    q = product(product((zero, sy, zero, cy), (sp, zero, zero, cp)), (zero, zero, sr, cr))
    q = np.stack(q, axis=-1)
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)


def export_animated_gltf(
    rig: BlendshapeRig,
    weights: Float[ArrayLike, "T K"],
    path: str | os.PathLike,
    *,
    fps: float = 60.0,
    times: Float[ArrayLike, " T"] | None = None,
    head_rotation: Float[ArrayLike, "T 3"] | None = None,
    name: str = "take",
    vertex_colors: Float[ArrayLike, "V C"] | None = None,
) -> Path:
    """Write ``rig`` with an animation of ``weights`` as a binary glTF 2.0 file, atomically.

    Args:
        rig: a ``BlendshapeRig`` with faces (any corrective order).
        weights: (T, K) rig weights per frame, in ``rig.names`` order (map a capture onto the
            rig first: ``capture.weights_for(rig.names)``), finite.
        path: the ``.glb`` to write.
        fps: frames per second when ``times`` is not given (frame t at t / fps seconds).
        times: (T,) strictly increasing key times in seconds (e.g. a take's timecodes, gaps
            kept); default ``arange(T) / fps``.
        head_rotation: optional (T, 3) yaw, pitch, roll in radians (see
            ``head_rotation_quaternions``), animating a parent node ``head``.
        name: the animation's name.
        vertex_colors: optional (V, 3) linear RGB in [0, 1] per vertex, written as the mesh's
            ``COLOR_0`` (e.g. an error map; ``canrig view`` shows it).

    Returns the path. The mesh's ``extras`` are those of ``export_gltf``; the animation's
    ``extras.fps`` records ``fps``.
    """
    _check_rig(rig, path)
    if rig.n_blendshapes == 0:
        raise ValueError("rig: has no blendshapes, nothing to animate (export_gltf writes it)")
    weights = np.asarray(weights)
    if weights.ndim != 2 or weights.shape[1] != rig.n_blendshapes or weights.shape[0] < 1:
        raise ValueError(
            f"weights: expected shape (T, {rig.n_blendshapes}) with T >= 1, got {weights.shape}"
        )
    check_real("weights", weights)
    check_finite("weights", weights)
    t = weights.shape[0]
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    if times is None:
        times = np.arange(t, dtype=np.float64) / fps
    times = np.asarray(times, np.float64)
    if times.shape != (t,) or not np.all(np.isfinite(times)):
        raise ValueError(f"times: expected ({t},) finite seconds, got shape {times.shape}")
    if t > 1 and np.any(np.diff(times) <= 0):
        raise ValueError("times: key times must increase strictly (glTF samplers require it)")
    if head_rotation is not None:
        head_rotation = np.asarray(head_rotation, np.float64)
        if head_rotation.shape != (t, 3) or not np.all(np.isfinite(head_rotation)):
            raise ValueError(
                f"head_rotation: expected ({t}, 3) finite yaw, pitch, roll in radians, "
                f"got shape {head_rotation.shape}"
            )

    if vertex_colors is not None:
        vertex_colors = np.asarray(vertex_colors)
        if vertex_colors.shape != (rig.n_vertices, 3):
            raise ValueError(
                f"vertex_colors: expected shape ({rig.n_vertices}, 3), got {vertex_colors.shape}"
            )
        check_real("vertex_colors", vertex_colors)
        check_finite("vertex_colors", vertex_colors)
        if vertex_colors.min() < 0 or vertex_colors.max() > 1:
            raise ValueError("vertex_colors: expected values in [0, 1]")

    document, buffer, _ = _rig_document(rig)
    if vertex_colors is not None:
        colors = buffer.add(vertex_colors.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER)
        document["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = colors
    morph = morph_target_weights(rig, weights)
    key_times = buffer.add(times.astype(np.float32), _FLOAT, "SCALAR", bounds=True)
    morph_values = buffer.add(morph.reshape(-1), _FLOAT, "SCALAR")
    samplers = [{"input": key_times, "output": morph_values, "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
    if head_rotation is not None:
        neutral = np.asarray(rig.neutral, np.float64)
        pivot = ((neutral.min(axis=0) + neutral.max(axis=0)) / 2).astype(np.float32)
        document["nodes"] = [
            {"name": "head", "translation": pivot.tolist(), "children": [1]},
            {"mesh": 0, "name": "rig", "translation": (-pivot).tolist()},
        ]
        quaternions = head_rotation_quaternions(head_rotation)
        rotation_values = buffer.add(quaternions, _FLOAT, "VEC4")
        samplers.append({"input": key_times, "output": rotation_values, "interpolation": "LINEAR"})
        channels[0]["target"]["node"] = 1
        channels.append({"sampler": 1, "target": {"node": 0, "path": "rotation"}})
    document["animations"] = [
        {"name": name, "samplers": samplers, "channels": channels, "extras": {"fps": fps}}
    ]
    return _write_glb(path, document, buffer)
