"""Shared fixtures of the rasteriser tests."""

from __future__ import annotations

import numpy as np
import pytest

from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate


@pytest.fixture(scope="session")
def head(data_dir):
    """The whole ICT head (17 parts) decimated to ~1,750 vertices (cm); built once for
    test_raster.py and test_hard.py."""
    ict = load_ict(data_dir, parts=None)
    d = decimate(ict.neutral, ict.faces, 1750)
    return np.asarray(d.vertices, np.float32), np.asarray(d.faces, np.int32)
