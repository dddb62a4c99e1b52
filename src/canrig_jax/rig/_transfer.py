"""Rigs on other meshes: a rig carried onto a remeshing, or transferred onto another head.

The geometry (surface maps, deformation transfer of per-vertex offsets) lives in
``canrig_jax.mesh``, which knows arrays only; these wrappers build the ``BlendshapeRig``.
"""

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from .._warnings import warn
from ..mesh import Remeshed, TriangleCorrespondence, transfer_deltas
from ._blendshape import BlendshapeRig, Corrective


def remesh_rig(rig: BlendshapeRig, remeshed: Remeshed) -> BlendshapeRig:
    """The rig carried onto the new triangulation: neutral = the remeshed vertices, deltas and
    correctives interpolated by the surface map (a ground-truth rig for the new mesh), in the
    rig's ``units``."""
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if not isinstance(remeshed, Remeshed):
        raise TypeError(f"remeshed: expected a Remeshed, got {type(remeshed).__name__}")
    surface_map = remeshed.map
    if surface_map.n_source != rig.n_vertices:
        raise ValueError(
            f"remeshed: maps from a mesh of {surface_map.n_source} vertices, the rig has "
            f"{rig.n_vertices}"
        )
    deltas = surface_map.carry(np.asarray(rig.deltas, np.float64))
    correctives = []
    for table in rig.correctives:
        dense = surface_map.carry(table.to_dense(rig.n_vertices).astype(np.float64))
        correctives.append(Corrective.from_dense(np.asarray(table.indices), dense))
    return BlendshapeRig(
        np.asarray(remeshed.vertices, np.float32),
        deltas.astype(np.float32),
        tuple(correctives),
        rig.names,
        remeshed.faces.astype(np.int32),
        units=rig.units,
    )


def deformation_transfer(
    source_rig: BlendshapeRig,
    target_neutral: Float[ArrayLike, "Vt 3"],
    correspondence: TriangleCorrespondence,
    *,
    screening: float = 1e-3,
    min_area: float = 1e-10,
    batch_size: int = 8,
    static_below: float | None = None,
    static_parts: Int[ArrayLike, " Vs"] | None = None,
) -> BlendshapeRig:
    """Transfer every blendshape of ``source_rig`` onto ``target_neutral``
    (Sumner & Popović 2004; the geometry is ``canrig_jax.mesh.transfer_deltas``).
    ``static_below`` (target units) anchors, per blendshape, the vertices whose carried source
    delta is shorter at zero (anchored transfer; None: plain); ``static_parts`` ((Vs,) source
    part labels, -1: per vertex) holds a target vertex only when its whole source part is still
    (per-part anchoring; ``transfer_deltas``).

    Returns a linear ``BlendshapeRig`` on the target (same names, target faces). Correctives of
    the source are not transferred (a warning says so).
    """
    if not isinstance(source_rig, BlendshapeRig):
        raise TypeError(f"source_rig: expected a BlendshapeRig, got {type(source_rig).__name__}")
    if source_rig.faces is None:
        raise ValueError("source_rig: deformation transfer needs a rig with faces")
    if source_rig.correctives:
        warn(
            "source_rig: correctives are not transferred; the result is the linear rig",
        )
    deltas = transfer_deltas(
        np.asarray(source_rig.neutral),
        np.asarray(source_rig.deltas),
        np.asarray(source_rig.faces),
        target_neutral,
        correspondence,
        screening=screening,
        min_area=min_area,
        batch_size=batch_size,
        static_below=static_below,
        static_parts=static_parts,
    )
    return BlendshapeRig(
        np.asarray(target_neutral, np.float32),
        deltas.astype(np.float32),
        (),
        source_rig.names,
        np.asarray(correspondence.target_faces, np.int32),
    )
