"""Mesh geometry: topology and deformation gradients."""

from .deformation_gradient import (
    DeformationGradientBlend,
    FallbackCounts,
    deformation_gradient_blend,
    mesh_fingerprint,
    triangle_edges,
)
from .operators import (
    MeshGeometry,
    MeshOperators,
    SparseMatrix,
    check_mesh,
    mesh_geometry,
    mesh_operators,
    pad_vertices,
    stack_operators,
)
from .remesh import (
    Remeshed,
    SurfaceMap,
    closest_surface_points,
    decimate,
    flip_quad_split,
    remesh_rig,
    subdivide,
)
from .topology import connected_components, vertex_adjacency
from .transfer import (
    TriangleCorrespondence,
    closest_point_correspondence,
    deformation_transfer,
    identity_correspondence,
    similarity_transform,
)

__all__ = [
    "DeformationGradientBlend",
    "FallbackCounts",
    "connected_components",
    "deformation_gradient_blend",
    "mesh_fingerprint",
    "triangle_edges",
    "vertex_adjacency",
]

__all__ += [
    "MeshGeometry",
    "MeshOperators",
    "Remeshed",
    "SparseMatrix",
    "SurfaceMap",
    "TriangleCorrespondence",
    "check_mesh",
    "closest_point_correspondence",
    "closest_surface_points",
    "decimate",
    "deformation_transfer",
    "flip_quad_split",
    "identity_correspondence",
    "mesh_geometry",
    "mesh_operators",
    "pad_vertices",
    "remesh_rig",
    "similarity_transform",
    "stack_operators",
    "subdivide",
]
