"""Vertex adjacency in the layouts the replay kernels walk (replay.cl).

Both tables are CSR lists over vertices, built once per engine from the triangles:

- :func:`vertex_face_ring`: every incident face as its own (a, b) pair, for sums that need each
  face's coefficients (the local-strain kernel);
- :func:`vertex_fans`: the same faces chained around the vertex, each neighbour listed once per
  fan, for the area-weighted normal: Σ cross(d_i, d_{i+1}) over consecutive neighbours needs one
  load and difference per neighbour, not two per face.
"""

from __future__ import annotations

import numpy as np


def _incident_pairs(faces: np.ndarray):
    """Per corner of every face: (vertex, next corner, the one after) in the face's winding, sorted
    by vertex (stable: a vertex's faces in face order)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    v = faces.ravel()
    a = np.roll(faces, -1, axis=1).ravel()
    b = np.roll(faces, -2, axis=1).ravel()
    order = np.argsort(v, kind="stable")
    return v[order], a[order], b[order]


def _csr_offsets(counts: np.ndarray) -> np.ndarray:
    ptr = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr


def vertex_face_ring(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertex→face adjacency as a CSR list of (a, b) pairs, for gathering normals.

    Parameters
    ----------
    faces : (T, 3) int triangles; n_vertices : V.

    Returns
    -------
    ptr : (V + 1,) int32 offsets; ring : (3T, 2) int32. For ``i`` in ``ptr[v]:ptr[v+1]``,
        (v, ring[i, 0], ring[i, 1]) is an incident face in its own winding (a rotation of the
        face), so cross(p_a − p_v, p_b − p_v) is that face's area-weighted normal.

    Example
    -------
    >>> ptr, ring = vertex_face_ring(np.array([[0, 1, 2]]), 3)
    >>> ptr.tolist(), ring.tolist()
    ([0, 1, 2, 3], [[1, 2], [2, 0], [0, 1]])
    """
    v, a, b = _incident_pairs(faces)
    ptr = _csr_offsets(np.bincount(v, minlength=n_vertices))
    return ptr.astype(np.int32), np.stack([a, b], axis=1).astype(np.int32)


def vertex_fans(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's incident faces chained into fans: (ptr (V + 1,) int32, fan (N,) int32).

    A vertex's entries ``fan[ptr[v]:ptr[v+1]]`` are neighbours; an entry ``j ≥ 0`` closes the face
    (v, previous entry, j), an entry ``j < 0`` starts a new fan at neighbour ``~j`` (no face
    before it). A closed fan (an interior vertex) lists its first neighbour again at its end;
    an open one (the mesh border) does not. Faces whose neighbours do not chain (non-manifold
    vertices, flipped winding) form fans of their own, so every incident face appears exactly
    once, in its own winding: the sum of cross(p_prev − p_v, p_j − p_v) over the entries j ≥ 0 is
    the same area-weighted normal as over :func:`vertex_face_ring`.

    Example
    -------
    >>> ptr, fan = vertex_fans(np.array([[0, 1, 2], [0, 2, 3]]), 4)
    >>> fan[ptr[0]:ptr[1]].tolist()         # fan 1, 2, 3 around vertex 0 (~1 = -2: a start)
    [-2, 2, 3]
    """
    v, a, b = _incident_pairs(faces)
    n = v.shape[0]
    if n == 0:
        return np.zeros(n_vertices + 1, np.int32), np.zeros(0, np.int32)
    following = _following_face(v, a, b, n_vertices)
    # every chain ends somewhere: cut each cycle (a closed fan) after its lowest entry's predecessor
    hops = max(1, int(np.ceil(np.log2(int(np.bincount(v).max()) + 1))))  # 2^hops ≥ the longest fan
    jump = np.append(np.where(following < 0, n, following), n)
    lowest = np.append(np.arange(n), n)
    ends = np.append(following < 0, True)
    for _ in range(hops):  # pointer doubling
        lowest = np.minimum(lowest, lowest[jump])
        ends |= ends[jump]
        jump = jump[jump]
    following = np.where(~ends[:n] & (following == lowest[:n]), -1, following)
    # list ranking: each entry's fan (named by its last entry) and its distance to that end
    last = np.where(following < 0, np.arange(n), following)
    to_end = (following >= 0).astype(np.int64)
    for _ in range(hops):
        to_end = to_end + to_end[last]
        last = last[last]
    # fans one after another in the order of their last entries (so each vertex's are together,
    # the entries being sorted by vertex), each led by its start marker
    tails = np.flatnonzero(following < 0)
    length = np.bincount(last, minlength=n)  # entries of each fan, at its last entry
    offset = np.zeros(n, dtype=np.int64)
    offset[tails] = np.cumsum(length[tails] + 1) - (length[tails] + 1)
    fan_length = length[last]
    at = offset[last] + fan_length - to_end  # 1 + the entry's place in its fan
    fan = np.empty(n + tails.shape[0], dtype=np.int64)
    fan[at] = b
    heads = to_end == fan_length - 1
    fan[at[heads] - 1] = ~a[heads]
    ptr = _csr_offsets(np.bincount(v, minlength=n_vertices) + np.bincount(v[tails], minlength=n_vertices))
    return ptr.astype(np.int32), fan.astype(np.int32)


def _following_face(v: np.ndarray, a: np.ndarray, b: np.ndarray, n_vertices: int) -> np.ndarray:
    """For each incident face (v, a, b): the index of the face (v, b, c) that follows it around v,
    or −1 where there is none or it is ambiguous (two faces would follow, or two precede)."""
    key_a = v * n_vertices + a
    by_a = np.argsort(key_a, kind="stable")  # nearly sorted already (by vertex): a merge pass
    sorted_a = key_a[by_a]
    repeated = np.zeros(len(sorted_a) + 1, dtype=bool)  # (one past the end: not found)
    repeated[1:-1] = sorted_a[1:] == sorted_a[:-1]
    repeated[:-2] |= repeated[1:-1]
    repeated[-1] = True
    key_b = v * n_vertices + b
    at = np.searchsorted(sorted_a, key_b)
    found = ~repeated[at]
    found[found] = sorted_a[at[found]] == key_b[found]
    following = np.where(found, by_a[np.minimum(at, len(by_a) - 1)], -1)
    # two faces followed by the same one: neither chains
    shared = np.bincount(following[found], minlength=len(v)) > 1
    following[found & shared[np.maximum(following, 0)]] = -1
    return following
