"""Where the real assets live.

The data folder is resolved, in order, from an explicit argument, the ``CANRIG_DATA``
environment variable, and ``../shared/data`` relative to the project root (the folder
holding ``pyproject.toml``). Nothing here copies data into the repository.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "CANRIG_DATA"
PROJECT_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_DATA_DIR = PROJECT_ROOT.parent / "shared" / "data"


def resolve_data_dir(data_dir: str | os.PathLike | None = None) -> Path:
    """Return the data folder: ``data_dir``, else ``$CANRIG_DATA``, else ``../shared/data``.

    Raises:
        FileNotFoundError: naming all three places when the chosen folder does not exist.
    """
    if data_dir is not None:
        chosen, source = Path(data_dir), "the data_dir argument"
    elif os.environ.get(ENV_VAR):
        chosen, source = Path(os.environ[ENV_VAR]), f"${ENV_VAR}"
    else:
        chosen, source = DEFAULT_DATA_DIR, "the default ../shared/data"
    if not chosen.is_dir():
        raise FileNotFoundError(
            f"canrig_jax data folder not found at {chosen} (taken from {source}). "
            f"Pass data_dir=..., or set the {ENV_VAR} environment variable, or place the "
            f"shared data at {DEFAULT_DATA_DIR} (../shared/data relative to the project root)."
        )
    return chosen


def data_file(relative: str, data_dir: str | os.PathLike | None = None) -> Path:
    """Path of one file inside the data folder; a clear error if it is missing."""
    path = resolve_data_dir(data_dir) / relative
    if not path.exists():
        raise FileNotFoundError(f"expected data file {relative!r} in {path.parent}, not found")
    return path
