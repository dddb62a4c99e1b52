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


def update_results(
    folder: str | os.PathLike,
    key: str,
    value: Any,
    *,
    table: str | None = None,
    merge: bool = False,
) -> Path:
    """Set ``results.json[key] = value`` in ``folder`` and keep every other key (written
    atomically), so that sibling experiment scripts share one results file.

    ``merge=True`` updates a dict entry instead of replacing it (e.g. adding timings to
    ``timing``). ``table``, when given, replaces the section of ``table.md`` between the
    markers ``<!-- section: key -->`` and ``<!-- end: key -->`` (appended when absent), so a
    script that rewrites ``table.md`` can keep the sections of the others (``table_sections``).
    """
    folder = Path(folder)
    path = folder / "results.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    if merge and isinstance(results.get(key), dict):
        results[key] = {**results[key], **value}
    else:
        results[key] = value
    save_json(path, results)
    if table is not None:
        table_path = folder / "table.md"
        text = table_path.read_text() if table_path.is_file() else ""
        sections = table_sections(text)
        sections[key] = table
        save_text(table_path, with_sections(text, sections))
    return path


def save_results(folder: str | os.PathLike, results: dict, table: str) -> Path:
    """Write an experiment's ``results.json`` and ``table.md`` in ``folder`` (atomically),
    keeping what sibling scripts added with ``update_results``: their keys (a dict entry both
    wrote is merged, the new values winning) and their marked table sections."""
    folder = Path(folder)
    path = folder / "results.json"
    old = json.loads(path.read_text()) if path.is_file() else {}
    merged = {**old, **results}
    for key, value in results.items():
        if isinstance(value, dict) and isinstance(old.get(key), dict):
            merged[key] = {**old[key], **value}
    save_json(path, merged)
    table_path = folder / "table.md"
    sections = table_sections(table_path.read_text()) if table_path.is_file() else {}
    save_text(table_path, with_sections(table, sections) if sections else table)
    return path


_SECTION_START = "<!-- section: {key} -->"
_SECTION_END = "<!-- end: {key} -->"


def table_sections(text: str) -> dict[str, str]:
    """The marked sections of a ``table.md`` text, by key, in order (see ``update_results``)."""
    sections: dict[str, str] = {}
    rest = text
    while (start := rest.find("<!-- section: ")) >= 0:
        close = rest.find(" -->", start)
        key = rest[start + len("<!-- section: ") : close]
        end = rest.find(_SECTION_END.format(key=key), close)
        if end < 0:
            break
        sections[key] = rest[close + len(" -->") : end].strip("\n") + "\n"
        rest = rest[end + len(_SECTION_END.format(key=key)) :]
    return sections


def _strip_section(text: str, key: str) -> str:
    start = text.find(_SECTION_START.format(key=key))
    end = text.find(_SECTION_END.format(key=key))
    if start < 0 or end < 0:
        return text
    return text[:start] + text[end + len(_SECTION_END.format(key=key)) :]


def with_sections(text: str, sections: dict[str, str]) -> str:
    """``text`` without its marked sections, then ``sections`` appended as marked blocks."""
    body = text
    for key in table_sections(text):
        body = _strip_section(body, key)
    return (
        body.rstrip("\n")
        + "\n\n"
        + "\n".join(
            f"{_SECTION_START.format(key=k)}\n{v.rstrip()}\n{_SECTION_END.format(key=k)}\n"
            for k, v in sections.items()
        )
    )
