"""Mesh geometry: topology, edges and geodesics, operators, deformation gradients, remeshing.

The layer above ``data``: it knows arrays (vertices, faces, per-vertex data) and nothing of
rigs; ``canrig_jax.rig`` builds rigs from it.

Also importable here but not in ``__all__`` (the checks and pieces the other subpackages build
on): ``SimilarityFit``, ``TriangleCorrespondence``, ``check_mesh``, ``connected_components``,
``edge_stretch``, ``fit_landmarks``, ``flip_quad_split``, ``mesh_edges``, ``rigid_residual``,
``similarity_icp``, ``similarity_transform``, ``subdivide``, ``transfer_deltas``,
``triangulate_quads``, ``vertex_adjacency``."""

from ._align import SimilarityFit as SimilarityFit
from ._align import bind_points
from ._align import fit_landmarks as fit_landmarks
from ._align import similarity_icp as similarity_icp
from ._checks import check_mesh as check_mesh
from ._deformation_gradient import DeformationGradientBlend
from ._geodesic import (
    attached_edge_graph,
    bridged_edge_graph,
    edge_graph,
    farthest_point_vertices,
    weighted_geodesic_distance,
)
from ._geodesic import mesh_edges as mesh_edges
from ._motion import edge_stretch as edge_stretch
from ._motion import flipped_triangles, self_intersections
from ._motion import rigid_residual as rigid_residual
from ._operators import MeshOperators, mesh_operators, pad_vertices, stack_operators
from ._remesh import Remeshed, SurfaceMap, decimate
from ._remesh import flip_quad_split as flip_quad_split
from ._remesh import subdivide as subdivide
from ._topology import connected_components as connected_components
from ._topology import vertex_adjacency as vertex_adjacency
from ._transfer import TriangleCorrespondence as TriangleCorrespondence
from ._transfer import closest_point_correspondence
from ._transfer import similarity_transform as similarity_transform
from ._transfer import transfer_deltas as transfer_deltas
from ._triangulate import triangulate_quads as triangulate_quads

__all__ = [
    "DeformationGradientBlend",
    "MeshOperators",
    "Remeshed",
    "SurfaceMap",
    "attached_edge_graph",
    "bind_points",
    "bridged_edge_graph",
    "closest_point_correspondence",
    "decimate",
    "edge_graph",
    "farthest_point_vertices",
    "flipped_triangles",
    "mesh_operators",
    "pad_vertices",
    "self_intersections",
    "stack_operators",
    "weighted_geodesic_distance",
]
