"""Atomic writes: nothing a user wrote is lost to an interrupted save."""

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


class CorruptFileError(ValueError):
    """A file exists but its bytes are damaged (truncated, flipped); the message names it."""


def _new_file_mode() -> int:
    """The permissions ``open(path, "w")`` would give a new file (0o666 minus the umask)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def check_output_path(path: Any, name: str = "path") -> Path:
    """``path`` as a Path; TypeError/OSError naming the argument ``name`` when a file cannot
    be written there (not a path, a folder, under a file, no permission)."""
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"{name}: expected a file path, got {type(path).__name__}")
    target = Path(path)
    if target.is_dir():
        raise IsADirectoryError(f"{name}: {target} is a folder, expected a file name")
    parent = target.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise NotADirectoryError(f"{name}: {parent} is a file, cannot hold {target}")
    if not os.access(parent, os.W_OK):
        raise PermissionError(f"{name}: cannot write in {parent} (no permission)")
    return target


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it over ``path`` only on success.

    The result keeps the permissions of the file it replaces, or gets those of a newly
    created file (not ``mkstemp``'s owner-only 0o600)."""
    path = check_output_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as error:  # a folder that cannot be made or written in (/proc, read-only)
        named = type(error)(f"path: cannot write {path} ({error.strerror or error})")
        named.errno = error.errno
        raise named from error
    os.close(fd)
    try:
        yield Path(tmp)
        mode = path.stat().st_mode & 0o777 if path.exists() else _new_file_mode()
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def save_npz(path: str | os.PathLike, **arrays) -> Path:
    """Write arrays to ``path`` (.npz) atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return Path(path)


def save_json(path: str | os.PathLike, data: Any) -> Path:
    """Write JSON to ``path`` atomically (sorted keys are not imposed)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return Path(path)


def save_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)
