"""Strain features: relative stretch of the feature-graph edges between handles.

Bickel et al. 2008, §5.1: the pose of the face is described by f_i = (|p_a − p_b| − l_i) / l_i
over F feature edges (a, b) between markers. The vector is invariant under rigid motion
of the head and local to each region of the face, which is what makes the per-vertex
(weighted) pose space work.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from facepipe.errors import InputError
from facepipe.core.mesh import _sorted_unique


def edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Symmetric (V, V) sparse matrix of mesh-edge lengths (for geodesic distances)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    n = vertices.shape[0]
    # one int64 key per edge: a 1-D unique is ~10× faster than unique(axis=0), same (a, b) order
    key = _sorted_unique(e[:, 0] * max(n, 1) + e[:, 1])  # sort-based: ~3x numpy 2's hashed unique here
    e = np.stack([key // max(n, 1), key % max(n, 1)], axis=1)
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    # a zero-length edge would vanish from the sparse graph and cut it apart
    length = np.maximum(length, 1e-12)
    g = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


# from this many vertex × source pairs (and 8 sources), the Dijkstra runs start in the background
GEODESICS_IN_A_PROCESS = 2_000_000
# ... on an OpenCL CPU device where there is one (else in a second process)
GEODESICS_ON_DEVICE = True


def geodesic_from(graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf) -> np.ndarray:
    """Dijkstra distances along mesh edges from each source vertex.

    Returns
    -------
    (S, V) float64; ``inf`` beyond ``limit`` or in other components.
    """
    return Geodesics(graph, sources, limit).finish()


class Geodesics:
    """Dijkstra from many sources: started on construction, collected by :meth:`finish`.

    SciPy's Dijkstra holds the GIL, so threads would not help; 89 sources on a 530k-vertex
    mesh are ~11 s on one core. A large problem (``background``: by default from
    :data:`GEODESICS_IN_A_PROCESS` pairs on two cores or more) is started at once, to run while
    this process does other work:

    * on an OpenCL CPU device (``device``; by default where there is one,
      :mod:`facepipe.opencl.geodesics`): the same distances to the bit in half the CPU time, on
      the driver's threads;
    * else in a child process that takes the sources first to last, while :meth:`finish`
      takes them from the last down until the two meet, so neither waits for the other however
      busy this process was. The rows are written into one file-backed mapping; a source
      claimed by both at the same instant is computed twice, to the same values. If the child
      fails, its sources are computed here.

    A small problem is computed by :meth:`finish`. ``where`` says which ("opencl", "process",
    "here"). The distances are kept for later calls of :meth:`finish` until :meth:`close`.
    """

    def __init__(self, graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf,
                 background: bool | None = None, device: bool | None = None):
        from facepipe.pipeline.background import BackgroundCall

        self.graph = graph = sp.csr_matrix(graph)
        self.sources = np.asarray(sources, dtype=np.int64)
        self.n_vertices = graph.shape[0]
        self.child_sources = 0
        self.where = "here"
        if background is None:
            background = len(self.sources) >= 8 and (os.cpu_count() or 1) >= 2 and \
                self.n_vertices * len(self.sources) >= GEODESICS_IN_A_PROCESS
        self._dir = self._child = self._result = self._device = None
        self._closed = False
        self._args = (graph, self.sources, limit)
        if not background:
            return
        if (GEODESICS_ON_DEVICE if device is None else device) and np.isinf(limit):
            from facepipe.opencl.geodesics import start

            self._device = start(graph, self.sources)
            if self._device is not None:
                self.where = "opencl"
                return
        try:
            self._paths = self._shared_files(len(self.sources), self.n_vertices)
        except OSError:  # no room for the shared rows (the child and this process write them): all here
            return
        self._args = (graph, self.sources, limit) + self._paths
        self._child = BackgroundCall(_claimed_rows, *self._args, 0)
        self.where = "process"

    def _shared_files(self, n_sources: int, n_vertices: int) -> tuple[str, str]:
        """The distance rows and the claims, as files both processes map. The space is allocated now:
        a write into a mapped file that the disk cannot hold would kill the process (SIGBUS)."""
        import tempfile

        self._dir = tempfile.TemporaryDirectory(prefix="facepipe-geodesics-")
        try:
            paths = (os.path.join(self._dir.name, "distances.npy"), os.path.join(self._dir.name, "claims.npy"))
            for path, dtype, shape in ((paths[0], np.float64, (n_sources, n_vertices)),
                                       (paths[1], np.uint8, (2, n_sources))):
                np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
                if hasattr(os, "posix_fallocate"):
                    fd = os.open(path, os.O_RDWR)
                    try:
                        os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
                    finally:
                        os.close(fd)
            return paths
        except OSError:
            self._dir.cleanup()
            self._dir = None
            raise

    def finish(self) -> np.ndarray:
        """Compute the sources the child has not reached, wait for it, return the (S, V) distances."""
        if self._result is not None:
            return self._result
        if self._closed:
            raise RuntimeError("the geodesics were closed before they were finished")
        if self._device is not None:
            try:
                self._result = self._device.finish()
            except Exception:  # noqa: BLE001 - the driver failed at run time: the same rows by SciPy
                self.where = "here after the device failed"
            finally:
                self._device.close()
                self._device = None
            if self._result is not None:
                return self._result
        if self._child is None:
            self._result = dijkstra_rows(*self._args[:3])
            return self._result
        try:
            _claimed_rows(*self._args, 1)
            self._child.result()
            claims = np.load(self._paths[1])
            self.child_sources = int((claims[0] & ~claims[1]).sum())
            rows = np.load(self._paths[0], mmap_mode="r")
            # POSIX keeps a mapping valid after its file is removed: no copy of the rows (0.4 GB at
            # 530k vertices); elsewhere they are copied out before the files go
            self._result = rows.view(np.ndarray) if os.name == "posix" else np.array(rows)
        finally:
            self._stop()
        return self._result

    def close(self) -> None:
        """Stop the child if it still runs (an error, or the result not wanted), remove the files and
        let go of the distances."""
        self._stop()
        self._result = None
        self._closed = True

    def _stop(self) -> None:
        if self._device is not None:
            self._device.close()
            self._device = None
        if self._child is not None:
            self._child.cancel()
            self._dir.cleanup()


def _claimed_rows(graph, sources, limit, distances_path, claims_path, side: int) -> int:
    """Dijkstra rows of the sources not claimed by the other side: side 0 from the first source up,
    side 1 from the last down, each stopping where the other has been. Returns the rows computed."""
    distances = np.load(distances_path, mmap_mode="r+")
    claims = np.load(claims_path, mmap_mode="r+")
    order = range(len(sources)) if side == 0 else range(len(sources) - 1, -1, -1)
    done = 0
    for i in order:
        if claims[1 - side, i]:
            break
        claims[side, i] = 1
        distances[i] = dijkstra_rows(graph, sources[i:i + 1], limit)[0]
        done += 1
    # no flush: both processes share the mapping's pages, and the file is removed before the
    # kernel would write them back, so the rows never go to the disk
    return done


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
