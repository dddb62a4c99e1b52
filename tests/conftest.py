"""Shared pytest fixtures."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from canrig_jax.data import load_livelinkface, resolve_data_dir


@pytest.fixture(scope="session")
def data_dir():
    """The real-data folder (argument, ``$CANRIG_DATA`` or ``../shared/data``)."""
    return resolve_data_dir()


@pytest.fixture(scope="session")
def _ict_quartic_build(data_dir):
    from canrig_jax.rig import ict_quartic_rig

    # Cached on disk (~/.cache/canrig_jax or $CANRIG_CACHE): ~45 s once per machine, then ~1 s.
    return ict_quartic_rig(data_dir, progress=False)


@pytest.fixture(scope="session")
def ict_quartic(_ict_quartic_build):
    """The standard ict-quartic rig (ICT face part, correctives up to order 4; cm)."""
    return _ict_quartic_build[0]


@pytest.fixture(scope="session")
def ict_quartic_report(_ict_quartic_build):
    """The ``SynthesisReport`` of the ict-quartic rig (from the cache when hit)."""
    return _ict_quartic_build[1]


@pytest.fixture(scope="session")
def ict_quartic_problem(ict_quartic):
    """``inverse.prepare(ict_quartic)``: Gram matrix, supports, LMMM bounds (~5 s)."""
    from canrig_jax import inverse

    return inverse.prepare(ict_quartic)


@pytest.fixture(scope="session")
def ict_face(data_dir):
    """The linear ICT rig on the face part (9,409 vertices, 53 expressions, faces; cm)."""
    from canrig_jax.rig import ict_linear_rig

    return ict_linear_rig(data_dir)


@pytest.fixture(scope="session")
def livelink_weights(data_dir, ict_face):
    """(180, 53) float32 Live Link Face frames retargeted onto the ICT channels."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        return load_livelinkface(data_dir).weights_for(ict_face.names)


@pytest.fixture(scope="session")
def sparse_poses(ict_face):
    """(16, 53) float32 random sparse poses: 3..10 active channels, weights in (0, 1]."""
    rng = np.random.default_rng(20240601)
    k = ict_face.n_blendshapes
    poses = np.zeros((16, k), np.float32)
    for row in poses:
        active = rng.choice(k, size=rng.integers(3, 11), replace=False)
        row[active] = rng.uniform(0.05, 1.0, active.size)
    return poses


@pytest.fixture(scope="session")
def ict_face_blend(ict_face):
    """The deformation-gradient blend of all 53 ICT expressions on the face part (~7 s)."""
    from canrig_jax.mesh import DeformationGradientBlend

    return DeformationGradientBlend(
        np.asarray(ict_face.neutral), np.asarray(ict_face.deltas), np.asarray(ict_face.faces)
    )
