"""A NumPy reference of the PSE / WPSE equations (float64), for tests and timing tables.

Same equations as ``_pse.py`` and ``_frames.py``, written directly in NumPy: per-vertex
squared distances, Gaussian basis matrices, batched ``np.linalg.solve``, frames from incident
triangle normals and a neighbour edge.
"""

import time

import jax
import numpy as np
from jaxtyping import ArrayLike, Float, Float64, Int

from ..._threads import single_threaded_blas
from ...wpse._pse import PoseSpaceEdit, apply


def reference_coefficients(
    metric: Float[ArrayLike, "Sm K"],
    poses: Float[ArrayLike, "P K"],
    displacements: Float[ArrayLike, "S P 3"],
    sigma: Float[ArrayLike, ""],
    ridge: float = 0.0,
) -> Float64[np.ndarray, "S P 3"]:
    """(S, P, 3) X_v = (Phi_v + ridge I)^{-1} D_v with Phi from the (S or 1, K) metric."""
    metric = np.asarray(metric, np.float64)
    poses = np.asarray(poses, np.float64)
    displacements = np.asarray(displacements, np.float64)
    diff_sq = (poses[:, None, :] - poses[None, :, :]) ** 2  # (P, P, K)
    distance_sq = np.einsum("sk,pqk->spq", metric, diff_sq)
    phi = np.exp(-distance_sq / (2.0 * sigma**2)) + ridge * np.eye(poses.shape[0])
    phi = np.broadcast_to(phi, (displacements.shape[0],) + phi.shape[1:])
    return np.linalg.solve(phi, displacements)


def reference_frames(
    posed: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    vertices: Int[ArrayLike, " S"],
    neighbour: Int[ArrayLike, " S"],
) -> Float64[np.ndarray, "S 3 3"]:
    """(S, 3, 3) frames [tangent, bitangent, normal] as columns, from the full (F, 3) face
    list: area-weighted normal of the triangles around each vertex, tangent towards
    ``neighbour`` projected onto the tangent plane."""
    posed = np.asarray(posed, np.float64)
    faces, vertices, neighbour = np.asarray(faces), np.asarray(vertices), np.asarray(neighbour)
    out = np.empty((len(vertices), 3, 3))
    for s, v in enumerate(np.asarray(vertices)):
        tri = posed[faces[np.any(faces == v, axis=1)]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
        normal /= np.linalg.norm(normal)
        edge = posed[neighbour[s]] - posed[v]
        tangent = edge - edge @ normal * normal
        tangent /= np.linalg.norm(tangent)
        out[s] = np.stack([tangent, np.cross(normal, tangent), normal], axis=-1)
    return out


def reference_vertex_frames(
    posed: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    vertices: Int[ArrayLike, " S"],
    neighbour: Int[ArrayLike, " S"],
) -> Float64[np.ndarray, "S 3 3"]:
    """(S, 3, 3) frames like ``reference_frames``, vectorised: every triangle's normal
    accumulated onto its three vertices over the whole mesh (np.add.at), in float64."""
    posed = np.asarray(posed, np.float64)
    faces, vertices, neighbour = np.asarray(faces), np.asarray(vertices), np.asarray(neighbour)
    p0, p1, p2 = (posed[faces[:, j]] for j in range(3))
    face_normal = np.cross(p1 - p0, p2 - p0)
    vertex_normal = np.zeros_like(posed)
    for j in range(3):
        np.add.at(vertex_normal, faces[:, j], face_normal)
    normal = vertex_normal[vertices]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    edge = posed[neighbour] - posed[vertices]
    tangent = edge - np.sum(edge * normal, axis=1, keepdims=True) * normal
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return np.stack([tangent, np.cross(normal, tangent), normal], axis=-1)


def reference_correction(
    metric: Float[ArrayLike, "Sm K"],
    poses: Float[ArrayLike, "P K"],
    coefficients: Float[np.ndarray, "S P 3"],
    sigma: Float[ArrayLike, ""],
    weights: Float[ArrayLike, " K"],
) -> Float[np.ndarray, "S 3"]:
    """(S, 3) sum_i x_{v,i} exp(-||w - w_i||_v^2 / (2 sigma^2)) in the coefficients' axes."""
    distance_sq = np.asarray(metric) @ ((np.asarray(weights) - np.asarray(poses)) ** 2).T
    phi = np.exp(-distance_sq / (2.0 * sigma**2))
    return np.einsum("sp,spc->sc", np.broadcast_to(phi, coefficients.shape[:2]), coefficients)


class NumpyEditEvaluator:
    """Vectorised NumPy run time of a fitted ``PoseSpaceEdit`` (the timing baseline).

    Evaluates the same equations as ``pse.apply`` on the same float32 arrays."""

    def __init__(self, model: PoseSpaceEdit):
        self.poses = np.asarray(model.poses)
        self.metric = np.asarray(model.metric)
        self.coefficients = np.asarray(model.coefficients)
        self.sigma = float(model.sigma)
        self.vertices = np.asarray(model.vertices)
        self.frames = model.frames
        if model.frames is not None:
            self.faces = np.asarray(model.frames.faces)
            self.incident = np.asarray(model.frames.incident)
            self.weight = np.asarray(model.frames.weight)
            self.neighbour = np.asarray(model.frames.neighbour)

    def __call__(
        self, weights: Float[np.ndarray, " K"], posed: Float[np.ndarray, "V 3"]
    ) -> Float[np.ndarray, "V 3"]:
        distance_sq = self.metric @ ((weights - self.poses) ** 2).T
        phi = np.exp(distance_sq * (-0.5 / self.sigma**2))
        offsets = np.einsum(
            "sp,scp->sc",
            np.broadcast_to(phi, (self.coefficients.shape[0], phi.shape[1])),
            self.coefficients,
        )
        if self.frames is not None:
            p0, p1, p2 = (posed[self.faces[:, j]] for j in range(3))
            face_normal = np.cross(p1 - p0, p2 - p0)
            normal = np.einsum("sd,sdc->sc", self.weight, face_normal[self.incident])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            edge = posed[self.neighbour] - posed[self.vertices]
            tangent = edge - np.sum(edge * normal, axis=1, keepdims=True) * normal
            tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
            bitangent = np.cross(normal, tangent)
            offsets = (
                offsets[:, :1] * tangent + offsets[:, 1:2] * bitangent + offsets[:, 2:] * normal
            )
        out = posed.copy()
        out[self.vertices] += offsets
        return out


def time_runtime(
    model: PoseSpaceEdit,
    weights: Float[ArrayLike, "T K"],
    posed: Float[ArrayLike, "T V 3"],
    passes: int = 5,
) -> dict:
    """Per-frame seconds of ``jax.jit(wpse.apply)`` (compiled first, one frame per call) and
    of ``NumpyEditEvaluator`` on the same frames, in this process.

    Args:
        model: a fitted ``PoseSpaceEdit``.
        weights: (T, K) probe poses; posed: (T, V, 3) the base rig at them.
        passes: passes over the T frames; JAX and NumPy alternate pass by pass, so both see
            the same spells of load on a shared machine. NumPy runs with one BLAS thread:
            a multi-threaded BLAS keeps its threads spinning after each call and took the
            second core from the JAX call timed next (on the 2-core machine JAX's median was
            0.5-1.1 ms lower with the reference on one thread, three paired runs).

    Returns ``jax_seconds`` and ``numpy_seconds`` ((passes * T,) arrays), ``batched_seconds``
    (per frame of ``jax.vmap(apply)`` over all T frames in one call, median of 5 calls: the
    cost of evaluating a whole take) and ``max_abs_diff`` between JAX and NumPy on the last
    frame (rig units).
    """
    if passes < 1:
        raise ValueError(f"passes: expected >= 1, got {passes}")
    weights, posed = np.asarray(weights), np.asarray(posed)
    run = jax.jit(apply)
    jax.block_until_ready(run(model, weights[0], posed[0]))
    reference = NumpyEditEvaluator(model)
    device_w, device_p = jax.device_put(weights), jax.device_put(posed)
    jax_seconds, numpy_seconds = [], []
    for _ in range(passes):
        for w, mesh in zip(device_w, device_p, strict=True):
            start = time.perf_counter()
            jax.block_until_ready(run(model, w, mesh))
            jax_seconds.append(time.perf_counter() - start)
        with single_threaded_blas():
            for w, mesh in zip(weights, posed, strict=True):
                start = time.perf_counter()
                expected = reference(w, mesh)
                numpy_seconds.append(time.perf_counter() - start)
    run_batch = jax.jit(jax.vmap(apply, (None, 0, 0)))
    jax.block_until_ready(run_batch(model, device_w, device_p))
    batched = []
    for _ in range(5):
        start = time.perf_counter()
        jax.block_until_ready(run_batch(model, device_w, device_p))
        batched.append((time.perf_counter() - start) / len(weights))
    difference = np.abs(np.asarray(run(model, weights[-1], posed[-1])) - expected).max()
    return {
        "jax_seconds": np.asarray(jax_seconds),
        "numpy_seconds": np.asarray(numpy_seconds),
        "batched_seconds": float(np.median(batched)),
        "max_abs_diff": float(difference),
    }
