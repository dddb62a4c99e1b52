"""Training checkpoints: one file, written atomically, that training resumes from exactly.

The file is a JSON header line (``{"format": ..., **state}``: options, step, elapsed time,
loss history) followed by the leaves of a pytree (model, optimiser state) serialised by
``eqx.tree_serialise_leaves``. The header alone rebuilds the pytree's structure.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import equinox as eqx

from .io import atomic_path


def save_checkpoint(path, tree, state: dict, format: str) -> Path:
    """Write ``state`` (JSON-able) and the array leaves of ``tree`` to ``path`` atomically."""
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, tree)
    header = json.dumps({"format": format, **state}).encode()
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header + b"\n")
        f.write(buffer.getvalue())
    return Path(path)


def read_checkpoint_state(path, format: str) -> dict:
    """The header of a checkpoint; ValueError when missing or of another format."""
    if not os.path.exists(path):
        raise ValueError(f"path: checkpoint {path} does not exist")
    with open(path, "rb") as f:
        try:
            state = json.loads(f.readline())
        except (json.JSONDecodeError, UnicodeDecodeError):
            state = {}
    if state.get("format") != format:
        raise ValueError(f"path: {path} is not a {format} checkpoint")
    return state


def load_checkpoint(path, like, format: str):
    """(tree, state) from ``save_checkpoint``; ``like`` gives the tree's structure."""
    state = read_checkpoint_state(path, format)
    with open(path, "rb") as f:
        f.readline()
        leaves = io.BytesIO(f.read())
    return eqx.tree_deserialise_leaves(leaves, like), state
