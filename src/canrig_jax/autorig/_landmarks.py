"""The ICT landmarks on any head, and its skin: the placement step ``auto_rig`` takes for every
method that carries the ICT template (``AbstractAutoRigMethod.needs_landmarks``), and that a
``Template`` takes for its own rig."""

import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from ..mesh import SimilarityFit, connected_components
from ._data import AutorigDataset, fit_head_landmarks
from ._orientation import inner_face


def skin_of(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Bool[np.ndarray, " V"]:
    """(V,) bool: the largest connected component (a head's skin; eyes, teeth, lashes are
    separate parts)."""
    labels = connected_components(np.asarray(faces), np.shape(vertices)[0])
    return labels == np.bincount(labels).argmax()


def place_landmarks(
    dataset: AutorigDataset,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    region: Bool[ArrayLike, " V"] | None = None,
) -> tuple[Int[np.ndarray, " L"], SimilarityFit, str]:
    """The ICT landmarks on a head (cm, +y up, facing +z): the ICT face part fitted by
    trimmed ICP (``fit_head_landmarks``); where that fails (a face-only mask, a stylised
    head), the inner face (eyes, nose, mouth; ``inner_face``) with a looser trim.

    Returns ((68,) vertex indices, the ``SimilarityFit``, "face" | "inner face"). Raises
    ValueError saying why and what to try when neither fits."""
    from ..mesh import fit_landmarks
    from ._orientation import FIT_TRIM

    if region is None:
        region = skin_of(vertices, faces)
    try:
        landmarks, fit = fit_head_landmarks(dataset, vertices, faces, region=region)
        return landmarks, fit, "face"
    except ValueError as first:
        head = dataset.head
        try:
            landmarks, fit = fit_landmarks(
                head.neutral,
                head.landmarks,
                inner_face(dataset),
                vertices,
                faces,
                target_region=region,
                trim=FIT_TRIM,
            )
            return landmarks, fit, "inner face"
        except ValueError as second:
            raise ValueError(
                f"vertices: the ICT face does not fit this head, whole ({first}) or by its "
                f"inner face ({str(second).replace('target_vertices', 'vertices')}). Is it a "
                "face in centimetres, y up, facing +z? Otherwise pass its landmarks by hand "
                "(landmarks=, 68 vertex indices) or carry from a template closer to its style "
                "(autorig.Transfer(template=...), canrig autorig --template)"
            ) from second
