"""Where the real assets live.

The data folder is resolved, in order, from an explicit argument, the ``CANRIG_DATA``
environment variable, and ``../shared/data`` relative to the project root (the folder
holding ``pyproject.toml``). Nothing here copies data into the repository.
"""

import os
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Shaped

from .._io import CorruptFileError

ENV_VAR = "CANRIG_DATA"
PROJECT_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_DATA_DIR = PROJECT_ROOT.parent / "shared" / "data"


def resolve_data_dir(data_dir: str | os.PathLike | None = None) -> Path:
    """Return the data folder: ``data_dir``, else ``$CANRIG_DATA``, else ``../shared/data``.

    Raises:
        FileNotFoundError: naming all three places when the chosen folder does not exist.
    """
    if data_dir is not None:
        if not isinstance(data_dir, str | os.PathLike):
            raise TypeError(f"data_dir: expected a folder path, got {type(data_dir).__name__}")
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


def read_arrays(
    path: str | os.PathLike, keys: Sequence[str]
) -> dict[str, Shaped[np.ndarray, "..."]]:
    """The arrays ``keys`` of the ``.npz`` file ``path``, read in full (no pickles).

    A damaged file (not a zip, truncated, a member failing its CRC) or one without an expected
    array raises ``CorruptFileError`` (a ValueError) naming the file and what was wrong."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise CorruptFileError(
                    f"{path}: corrupt or incomplete data file, arrays {missing} are missing "
                    f"(it has {sorted(z.files)})"
                )
            return {k: np.asarray(z[k]) for k in keys}
    except CorruptFileError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError, KeyError) as error:
        if isinstance(error, FileNotFoundError):
            raise
        raise CorruptFileError(
            f"{path}: corrupt data file ({type(error).__name__}: {error})"
        ) from error
