"""Strain features: relative stretch of the feature-graph edges between handles.

Bickel et al. 2008, §5.1: the pose of the face is described by f_i = (|p_a − p_b| − l_i) / l_i
over F feature edges (a, b) between markers. The vector is invariant under rigid motion
of the head and local to each region of the face, which is what makes the per-vertex
(weighted) pose space work.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from facepipe.errors import InputError
from facepipe.core.mesh import unique_edges


def edge_graph(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray | None = None) -> sp.csr_matrix:
    """Symmetric (V, V) sparse matrix of mesh-edge lengths (for geodesic distances).

    ``edges``: the faces' unique edges (:attr:`facepipe.core.mesh.Mesh.edges`) where already
    at hand; else they are found here."""
    vertices = np.asarray(vertices, dtype=np.float64)
    n = vertices.shape[0]
    e = unique_edges(np.asarray(faces, dtype=np.int64)) if edges is None else np.asarray(edges, dtype=np.int64)
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    # a zero-length edge would vanish from the sparse graph and cut it apart
    length = np.maximum(length, 1e-12)
    g = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


def dijkstra_rows(graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf) -> np.ndarray:
    """Dijkstra distances (S, V) from ``sources`` in this process."""
    # the graph is symmetric (edge_graph): the directed search gives the same distances without
    # SciPy symmetrising it first, ~20 % faster
    return dijkstra(graph, directed=True, indices=sources, limit=limit)


def auto_feature_graph(vertices: np.ndarray, faces: np.ndarray, marker_vertices: np.ndarray,
                       min_contact: int = 2, graph: sp.csr_matrix | None = None) -> np.ndarray:
    """Feature edges between markers whose geodesic Voronoi regions on the surface touch.

    This is the geodesic Delaunay graph of the markers: planar on the surface, it needs
    no UV layout or projection, and it never connects markers across a hole (the mouth,
    the eyes), where a straight-line Delaunay would.

    Parameters
    ----------
    vertices : (V, 3); faces : (T, 3); marker_vertices : (M,) vertex indices.
    min_contact : regions must share at least this many mesh edges (ignores corner contacts).
    graph : :func:`edge_graph` of the mesh, if already at hand.

    Returns
    -------
    edges : (F, 2) int64 marker indices (into ``marker_vertices``), a < b, sorted.
    """
    marker_vertices = np.asarray(marker_vertices, dtype=np.int64)
    if graph is None:
        graph = edge_graph(vertices, faces)
    # (the graph is symmetric: the directed search is the same, without SciPy symmetrising it)
    _, _, source = dijkstra(graph, directed=True, indices=marker_vertices, min_only=True,
                            return_predecessors=True)
    marker_of = np.full(len(vertices), -1, dtype=np.int64)
    marker_of[marker_vertices] = np.arange(len(marker_vertices))
    owner = np.where(source >= 0, marker_of[np.maximum(source, 0)], -1)
    coo = sp.triu(graph, k=1).tocoo()
    a, b = owner[coo.row], owner[coo.col]
    keep = (a >= 0) & (b >= 0) & (a != b)
    pairs = np.sort(np.stack([a[keep], b[keep]], axis=1), axis=1)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    uniq, counts = np.unique(pairs, axis=0, return_counts=True)
    return uniq[counts >= min_contact]


def graph_from_pairs(pairs: list[tuple[str, str]], marker_names: list[str], path: str = "") -> np.ndarray:
    """Feature edges from marker-name pairs (a CSV graph), validated.

    Returns
    -------
    edges : (F, 2) int64 marker indices, a < b, duplicates removed.
    """
    index = {name: i for i, name in enumerate(marker_names)}
    edges = []
    for line_no, (a, b) in enumerate(pairs, start=1):
        for name in (a, b):
            if name not in index:
                raise InputError(f"line {line_no}: marker {name!r} is not a handle marker of the rig", path=path,
                                 hint="use names from markers.csv (markers with role 'ignore' cannot be used)")
        if a == b:
            raise InputError(f"line {line_no}: feature edge joins marker {a!r} to itself", path=path)
        edges.append(sorted((index[a], index[b])))
    if not edges:
        raise InputError("the feature graph has no edges", path=path)
    return np.unique(np.asarray(edges, dtype=np.int64), axis=0)


def edge_lengths(marker_positions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Lengths of the feature edges, batched: (..., M, 3) → (..., F)."""
    d = marker_positions[..., edges[:, 0], :] - marker_positions[..., edges[:, 1], :]
    return np.sqrt(np.einsum("...i,...i->...", d, d))


def strain_features(marker_positions: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> np.ndarray:
    """Strain feature vectors f_i = (|p_a − p_b| − l_i) / l_i.

    Parameters
    ----------
    marker_positions : (..., M, 3) marker positions (any rigid frame).
    edges : (F, 2) marker index pairs; rest_lengths : (F,) rest lengths l_i.

    Returns
    -------
    (..., F) dimensionless; 0 at rest, > 0 stretched, < 0 compressed.

    Example
    -------
    >>> p = np.array([[0, 0, 0], [2, 0, 0.]]); strain_features(p, np.array([[0, 1]]), np.array([1.]))
    array([1.])
    """
    return (edge_lengths(marker_positions, edges) - rest_lengths) / rest_lengths
