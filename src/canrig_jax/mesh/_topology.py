"""Mesh connectivity: vertex graph and connected components (scipy.sparse.csgraph)."""

import numpy as np
import scipy.sparse as sp
from jaxtyping import ArrayLike, Int
from scipy.sparse.csgraph import connected_components as _csgraph_components


def vertex_adjacency(faces: Int[ArrayLike, "F 3"], n_vertices: int) -> sp.csr_matrix:
    """(V, V) symmetric 0/1 adjacency of the triangle edges."""
    faces = np.asarray(faces, np.int64)
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = sp.csr_matrix((np.ones(i.size), (i, j)), shape=(n_vertices, n_vertices))
    graph = ((graph + graph.T) > 0).astype(np.float64)
    return graph.tocsr()


def connected_components(faces: Int[ArrayLike, "F 3"], n_vertices: int) -> Int[np.ndarray, " V"]:
    """(V,) component label of each vertex (isolated vertices get their own label)."""
    _, labels = _csgraph_components(vertex_adjacency(faces, n_vertices), directed=False)
    return labels.astype(np.int32)
