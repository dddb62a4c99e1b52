"""Shared pytest fixtures."""

from __future__ import annotations

import pytest

from canrig_jax.data import resolve_data_dir


@pytest.fixture(scope="session")
def data_dir():
    """The real-data folder (argument, ``$CANRIG_DATA`` or ``../shared/data``)."""
    return resolve_data_dir()
