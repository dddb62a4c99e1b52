"""Fixtures of the WPSE tests: a tiny smooth rig on a grid, and real ICT edits."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.rig import BlendshapeRig


def grid_rig(n: int = 7, n_blendshapes: int = 4, seed: int = 0) -> BlendshapeRig:
    """An n x n vertex grid in the xy plane (slightly bumped in z) with smooth random
    blendshapes, each moving one region of the grid."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    neutral = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype(np.float32)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [(a, b, d), (a, d, c)]
    centres = rng.uniform(0, 1, (n_blendshapes, 2))
    falloff = np.exp(
        -((neutral[None, :, :2] - centres[:, None]) ** 2).sum(-1) / (2 * 0.15**2)
    )  # (K, V)
    direction = rng.normal(size=(n_blendshapes, 1, 3))
    deltas = (0.2 * falloff[..., None] * direction).astype(np.float32)
    return BlendshapeRig(neutral, deltas, (), tuple(f"s{k}" for k in range(n_blendshapes)), faces)


@pytest.fixture(scope="session")
def tiny_rig():
    return grid_rig()


@pytest.fixture(scope="session")
def tiny_edits(tiny_rig):
    """(P, K) distinct poses and (P, V, 3) smooth random edits on the tiny rig."""
    rng = np.random.default_rng(1)
    p, v = 5, tiny_rig.n_vertices
    poses = rng.uniform(0, 1, (p, tiny_rig.n_blendshapes)).astype(np.float32)
    edits = (0.05 * rng.normal(size=(p, 1, 3)) * rng.uniform(0.2, 1.0, (p, v, 1))).astype(
        np.float32
    )
    return poses, edits


@pytest.fixture(scope="session")
def real_edits(ict_face, livelink_weights, ict_face_blend):
    """Real edits on the ICT face: the deformation-gradient blend minus the linear rig at the
    8 Live Link frames where the linear rig is worst (at least 0.5 apart), and 16 other
    frames with their desired meshes for evaluation."""

    from canrig_jax.papers.wpse import select_edit_frames
    from canrig_jax.rig import evaluate_batch

    frames = livelink_weights[::3]  # 60 frames keep the blend cheap
    desired = ict_face_blend(frames).astype(np.float32)
    linear = np.asarray(evaluate_batch(ict_face, frames))
    error = np.linalg.norm(desired - linear, axis=-1).mean(axis=1)
    chosen = select_edit_frames(error, frames, 8, 0.5)
    rest = np.setdiff1d(np.arange(len(frames)), chosen)
    return {
        "poses": frames[chosen],
        "edits": desired[chosen] - linear[chosen],
        "linear": linear[chosen],
        "test_poses": frames[rest],
        "test_desired": desired[rest],
        "test_linear": linear[rest],
    }
