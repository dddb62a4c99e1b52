"""Mesh geometry: topology and deformation gradients."""

from .deformation_gradient import (
    DeformationGradientBlend,
    FallbackCounts,
    deformation_gradient_blend,
    mesh_fingerprint,
    triangle_edges,
)
from .topology import connected_components, vertex_adjacency

__all__ = [
    "DeformationGradientBlend",
    "FallbackCounts",
    "connected_components",
    "deformation_gradient_blend",
    "mesh_fingerprint",
    "triangle_edges",
    "vertex_adjacency",
]
