"""Mesh geometry: topology, edges and geodesics, operators, deformation gradients, remeshing.

The layer above ``data``: it knows arrays (vertices, faces, per-vertex data) and nothing of
rigs; ``canrig_jax.rig`` builds rigs from it."""

from .._cache import mesh_fingerprint
from ._align import SimilarityFit, bind_points, fit_landmarks, similarity_icp
from ._checks import check_mesh, check_vertices
from ._deformation_gradient import (
    DeformationGradientBlend,
    FallbackCounts,
    triangle_edges,
    triangle_frames,
)
from ._geodesic import (
    attached_edge_graph,
    bridged_edge_graph,
    edge_graph,
    farthest_point_vertices,
    mesh_edges,
    weighted_geodesic_distance,
)
from ._motion import (
    edge_stretch,
    flipped_triangles,
    rigid_residual,
    self_intersections,
)
from ._operators import (
    MeshGeometry,
    MeshOperators,
    SparseMatrix,
    compute_geometry,
    mesh_geometry,
    mesh_operators,
    pad_vertices,
    stack_operators,
)
from ._remesh import (
    Remeshed,
    SurfaceMap,
    closest_surface_points,
    decimate,
    flip_quad_split,
    quad_pairs,
    subdivide,
    vertex_surface_map,
)
from ._topology import connected_components, vertex_adjacency
from ._transfer import (
    TriangleCorrespondence,
    closest_point_correspondence,
    identity_correspondence,
    similarity_transform,
    transfer_deltas,
)
from ._triangulate import triangulate_quads as triangulate_quads

__all__ = [
    "compute_geometry",
    "quad_pairs",
    "DeformationGradientBlend",
    "FallbackCounts",
    "connected_components",
    "attached_edge_graph",
    "bridged_edge_graph",
    "edge_graph",
    "farthest_point_vertices",
    "mesh_edges",
    "weighted_geodesic_distance",
    "mesh_fingerprint",
    "triangle_edges",
    "vertex_adjacency",
]

__all__ += ["SimilarityFit", "bind_points", "fit_landmarks", "similarity_icp"]

__all__ += [
    "MeshGeometry",
    "MeshOperators",
    "Remeshed",
    "SparseMatrix",
    "SurfaceMap",
    "TriangleCorrespondence",
    "check_mesh",
    "check_vertices",
    "closest_point_correspondence",
    "closest_surface_points",
    "decimate",
    "flip_quad_split",
    "identity_correspondence",
    "mesh_geometry",
    "mesh_operators",
    "pad_vertices",
    "transfer_deltas",
    "triangle_frames",
    "vertex_surface_map",
    "similarity_transform",
    "stack_operators",
    "subdivide",
]

__all__ += [
    "edge_stretch",
    "flipped_triangles",
    "rigid_residual",
    "self_intersections",
]
