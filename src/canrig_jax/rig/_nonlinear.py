"""The nonlinear (deformation-gradient) blend of a rig's blendshapes, at the rig level.

The blend itself is geometry (``canrig_jax.mesh.DeformationGradientBlend``, arrays only);
this wrapper takes a ``BlendshapeRig`` and keeps the prefactorised blend of the last mesh.
"""

import numpy as np
from jaxtyping import ArrayLike, Float, Float64

from .._cache import fingerprint
from ..mesh import DeformationGradientBlend
from ._blendshape import BlendshapeRig

_BLEND_CACHE: dict[str, DeformationGradientBlend] = {}


def deformation_gradient_blend(
    rig: BlendshapeRig, weights: Float[ArrayLike, "*batch K"], **options
) -> Float64[np.ndarray, "*batch V 3"]:
    """Nonlinear blend of ``rig``'s blendshapes at ``weights`` (K,) or (B, K).

    The rig must carry ``faces``. The prefactorised blend is cached in memory per mesh.
    Returns (V, 3) or (B, V, 3) float64 vertices in rig units.
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if rig.faces is None:
        raise ValueError("rig: deformation_gradient_blend needs a rig with faces")
    arrays = [np.asarray(rig.neutral), np.asarray(rig.deltas), np.asarray(rig.faces)]
    key = fingerprint(*arrays) + repr(sorted(options.items()))
    if key not in _BLEND_CACHE:
        _BLEND_CACHE.clear()
        _BLEND_CACHE[key] = DeformationGradientBlend(*arrays, **options)
    return _BLEND_CACHE[key](weights)
