"""Where a result came from: the exact command, the git commit and the package versions.

Every experiment's results writer records ``provenance(command)`` in its ``results.json``
(key ``"provenance"``), and the committed folder under ``experiments/results/<name>/`` keeps
the command in a file named ``COMMAND`` (``COMMAND_FILE``).
"""

import importlib.metadata
import platform
import shlex
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from ._io import save_text

COMMAND_FILE = "COMMAND"
"""Name of the file holding the committed command(s) of an experiment's results folder."""

PACKAGES = (
    "canrig_jax",
    "jax",
    "jaxlib",
    "equinox",
    "optax",
    "optimistix",
    "lineax",
    "jaxopt",
    "numpy",
    "scipy",
    "trimesh",
    "robust_laplacian",
)
"""Packages whose versions ``provenance`` records."""

_REPO = Path(__file__).resolve().parents[2]


def experiment_command(script: str | Path, argv: Sequence[str] | None = None) -> str:
    """The command line that ran ``script`` with ``argv`` (default ``sys.argv[1:]``), as
    ``python <script relative to the repository> <args>``, shell-quoted."""
    path = Path(script).resolve()
    try:
        path = path.relative_to(_REPO)
    except ValueError:
        pass
    args = list(sys.argv[1:] if argv is None else argv)
    return shlex.join(["python", path.as_posix(), *map(str, args)])


def git_commit(repo: str | Path | None = None) -> tuple[str | None, bool | None]:
    """(HEAD commit, whether tracked files differ from it) of the repository, or
    (None, None) outside a git checkout."""
    cwd = Path(repo) if repo is not None else _REPO
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=cwd,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None, None
    return commit, bool(status.strip())


def package_versions(packages: Sequence[str] = PACKAGES) -> dict[str, str | None]:
    """Installed version of each package (None when not installed)."""
    out = {}
    for name in packages:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def record_command(folder: str | Path, command: str, note: str | None = None) -> Path:
    """Add ``command`` to ``folder``'s ``COMMAND`` file (written atomically) without losing
    what is there: a new file holds the command; an existing one keeps every line (other
    commands, comments on how the results were refreshed) and gets the command appended,
    after ``note`` as a ``#`` comment line if given, unless one of its lines already is that
    command. Returns the file's path."""
    path = Path(folder) / COMMAND_FILE
    lines = path.read_text().splitlines() if path.exists() else []
    if command.strip() not in (line.strip() for line in lines):
        lines += ([f"# {note}"] if note else []) + [command.strip()]
    return save_text(path, "\n".join(lines) + "\n")


def provenance(command: str) -> dict:
    """The record an experiment's ``results.json`` carries under ``"provenance"``: the command,
    the git commit (and whether the working tree had uncommitted changes to tracked files),
    package versions, Python and the platform."""
    if not isinstance(command, str) or not command.strip():
        raise ValueError(
            f"command: expected the command line as a non-empty string, got {command!r}"
        )
    commit, dirty = git_commit()
    return {
        "command": command,
        "git_commit": commit,
        "git_dirty": dirty,
        "versions": package_versions(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }


def with_provenance(results: dict, command: str) -> dict:
    """``results`` with ``"provenance": provenance(command)`` added (a new dict)."""
    return {**results, "provenance": provenance(command)}
