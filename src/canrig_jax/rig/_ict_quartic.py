"""The standard **ict-quartic** rig: the ICT face part with synthesised correctives.

Built once by ``synthesize_correctives`` on the deformation-gradient blend of ICT's 53
expressions, then cached on disk keyed by a hash of the inputs and options, so experiments
load it in about a second.
"""

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence

from .._cache import CACHE_ENV_VAR, build_lock, cache_dir, mesh_fingerprint
from .._io import save_json
from ..data import FACE, load_ict
from ._blendshape import BlendshapeRig
from ._io import load_rig, save_rig
from ._synthesis import SynthesisOptions, SynthesisReport, synthesize_correctives

SYNTHESIS_VERSION = 2
"""Bump when synthesis changes its output, to invalidate caches."""

__all__ = ["CACHE_ENV_VAR", "cache_dir", "ict_linear_rig", "ict_quartic_rig"]


def ict_linear_rig(
    data_dir: str | os.PathLike | None = None, parts: Sequence[str] | str | None = FACE
) -> BlendshapeRig:
    """The linear ICT rig (53 expressions) on ``parts`` (default the face, 9,409 vertices)."""
    model = load_ict(data_dir, parts=parts)
    return BlendshapeRig(model.neutral, model.deltas, (), model.names, model.faces)


def ict_quartic_rig(
    data_dir: str | os.PathLike | None = None,
    *,
    parts: Sequence[str] | str | None = FACE,
    options: SynthesisOptions | None = None,
    cache: str | os.PathLike | None = None,
    rebuild: bool = False,
    progress: bool = True,
) -> tuple[BlendshapeRig, SynthesisReport]:
    """The ICT rig with correctives up to order ``options.max_order`` (default 4), cached.

    Returns the rig (centimetres) and the synthesis report (from the cache when hit).
    """
    options = options or SynthesisOptions()
    linear = ict_linear_rig(data_dir, parts)
    assert linear.faces is not None  # the ICT rig carries its triangles
    mesh_key = mesh_fingerprint(linear.neutral, linear.deltas, linear.faces)
    recipe = f"{mesh_key}{dataclasses.asdict(options)}v{SYNTHESIS_VERSION}"
    key = hashlib.sha256(recipe.encode()).hexdigest()[:16]
    folder = cache_dir(cache)
    rig_path, report_path = folder / f"ict-quartic-{key}.npz", folder / f"ict-quartic-{key}.json"
    with build_lock(rig_path):  # another process building it: wait, then read its file
        if not rebuild and rig_path.exists() and report_path.exists():
            report = SynthesisReport(**_int_keys(json.loads(report_path.read_text())))
            return load_rig(rig_path), report
        rig, report = synthesize_correctives(linear, options, progress=progress)
        save_rig(rig_path, rig)
        save_json(report_path, dataclasses.asdict(report))
    return rig, report


def _int_keys(report: dict) -> dict:
    return {
        k: ({int(o): v for o, v in value.items()} if isinstance(value, dict) else value)
        for k, value in report.items()
    }
