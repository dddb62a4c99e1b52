"""canrig_jax: differentiable face rigs in JAX on real assets.

The package is its subpackages, each imported on first use (``import canrig_jax`` itself
loads neither JAX nor any of them):

- ``canrig_jax.data``: loaders for real assets (ICT, Live Link Face, MediaPipe, head files).
- ``canrig_jax.mesh``: mesh geometry (edges, geodesics, Laplacians, deformation gradients).
- ``canrig_jax.rig``: the ``BlendshapeRig`` pytree, ``evaluate``, correctives, glTF.
- ``canrig_jax.inverse``: inverse-rig solvers (``prepare`` -> ``solve``).
- ``canrig_jax.wpse``: weighted pose-space editing.
- ``canrig_jax.canrig``: CANRig's masked attention, models, training and workflows.
- ``canrig_jax.autorig``: RigAnyFace auto-rigging of a new head.
- ``canrig_jax.render``: figures and a differentiable rasteriser.
- ``canrig_jax.viewer``: a local web viewer for rigs and takes.
- ``canrig_jax.watchdog``: turns a run that stops progressing into a clear error.
- ``canrig_jax.distributed``: runs over several processes (``jax.distributed``).

Also here: ``CanrigWarning`` (every warning the library issues), ``CorruptFileError`` (a
file that is not what its name says), ``run_command(argv)`` (the ``canrig`` console script)
and ``__version__``.
"""

import importlib
import importlib.metadata
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ._io import CorruptFileError
from ._warnings import CanrigWarning

if TYPE_CHECKING:
    from . import (
        autorig,
        canrig,
        data,
        distributed,
        inverse,
        mesh,
        pbs,
        render,
        rig,
        viewer,
        watchdog,
        wpse,
    )

_SUBPACKAGES = frozenset(
    (
        "data",
        "mesh",
        "rig",
        "inverse",
        "wpse",
        "canrig",
        "pbs",
        "autorig",
        "render",
        "viewer",
        "watchdog",
        "distributed",
    )
)
"""The public subpackages, imported on first attribute access."""


def _version() -> str:
    """The installed distribution's version; from a source tree that is not installed, the
    ``version`` in ``pyproject.toml`` beside ``src/``."""
    try:
        return importlib.metadata.version("canrig_jax")
    except importlib.metadata.PackageNotFoundError:
        pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
        try:
            text = pyproject.read_text(encoding="utf-8")
        except OSError:
            return "0+unknown"
        match = re.search(r'^version\s*=\s*"([^"]+)"', text, re.M)
        return match.group(1) if match else "0+unknown"


__version__ = _version()


def run_command(argv: Sequence[str] | None = None) -> int:
    """Run the ``canrig`` command line with ``argv`` (default: ``sys.argv[1:]``); returns the
    exit status (0, or 2 on bad input, with one ``canrig: error: ...`` line on stderr)."""
    from ._commands import main

    return main(argv)


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        module = importlib.import_module(f"{__name__}.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*__all__, "__version__"])


__all__ = [
    "CanrigWarning",
    "CorruptFileError",
    "run_command",
    "data",
    "mesh",
    "rig",
    "inverse",
    "wpse",
    "canrig",
    "pbs",
    "autorig",
    "render",
    "viewer",
    "watchdog",
    "distributed",
]
