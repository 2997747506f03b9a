"""Per-vertex orthonormal frames of a deformed mesh, for storing details locally.

Fine-scale details live in the tangent frames of the large-scale surface, so a wrinkle
learned in one pose rotates with the skin in another (Bickel et al. 2008, §5).
Frame of vertex v: normal n (area-weighted face normals), tangent t from the edge to a
fixed neighbour projected into the tangent plane, bitangent b = n × t.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from facepipe.core.vectors import cross, lengths
from facepipe.parallel import map_blocks


def vertex_face_matrix(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, T) incidence matrix: summing face quantities onto vertices is one sparse product."""
    faces = np.asarray(faces, dtype=np.int64)
    # column by column (a face's three corners) and turned to rows: each row's faces in order,
    # as a coordinate list would give them, without its sort
    by_face = sp.csc_matrix((np.ones(faces.size), faces.ravel(), np.arange(0, faces.size + 1, 3)),
                            shape=(n_vertices, faces.shape[0]))
    return by_face.tocsr()


def frame_neighbors(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """A fixed neighbour per vertex (the lowest-index one) that defines its tangent.

    Returns
    -------
    (V,) int64; a vertex without neighbours gets itself (its frame falls back to a default).
    """
    faces = np.asarray(faces, dtype=np.int64)
    nb = np.full(n_vertices, np.iinfo(np.int64).max, dtype=np.int64)
    for k in range(3):  # each corner's lower-index neighbour in its face
        np.minimum.at(nb, faces[:, k], np.minimum(faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]))
    missing = nb == np.iinfo(np.int64).max
    nb[missing] = np.flatnonzero(missing)
    return nb


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals, batched.

    Parameters
    ----------
    vertices : (..., V, 3); faces : (T, 3); incidence : optional cached vertex_face_matrix.

    Returns
    -------
    (..., V, 3) unit normals in the dtype of ``vertices``.
    """
    vertices = np.asarray(vertices)
    n = vertices.shape[-2]
    if incidence is None:
        incidence = vertex_face_matrix(faces, n)
    lead = vertices.shape[:-2]
    # face normals on the faces' axis first, (T, batch, 3), so the sum over incident faces is one
    # sparse product for all frames at once: (V, T) @ (T, batch*3)
    corners = np.moveaxis(vertices, -2, 0)[np.asarray(faces).T]  # (3, T, ..., 3)
    corners[1] -= corners[0]
    corners[2] -= corners[0]
    fn = cross(corners[1], corners[2])
    vn = np.asarray(incidence @ fn.reshape(fn.shape[0], -1)).reshape((n,) + lead + (3,))
    vn = np.moveaxis(vn, 0, -2)
    return _normalize(vn, fallback=np.array([0.0, 0.0, 1.0])).astype(vertices.dtype, copy=False)


def _normalize(v: np.ndarray, fallback: np.ndarray, norm: np.ndarray | None = None) -> np.ndarray:
    """v / |v| over the last axis, ``fallback`` where |v| ≤ 1e-30 (``norm``: |v|, if at hand)."""
    norm = lengths(v, keepdims=True) if norm is None else norm
    ok = norm > 1e-30
    out = np.empty(v.shape, dtype=np.result_type(v, fallback))
    out[...] = fallback
    return np.divide(v, norm, out=out, where=ok)


def local_frames(vertices: np.ndarray, faces: np.ndarray, neighbors: np.ndarray,
                 incidence: sp.csr_matrix | None = None) -> np.ndarray:
    """Orthonormal frames [t, b, n] as matrix columns, batched.

    Parameters
    ----------
    vertices : (..., V, 3); faces : (T, 3); neighbors : (V,) from :func:`frame_neighbors`.

    Returns
    -------
    R : (..., V, 3, 3) with R[..., :, 0] = t, R[..., :, 1] = b, R[..., :, 2] = n;
        world = R @ local, local = Rᵀ @ world.
    """
    vertices = np.asarray(vertices)
    if vertices.ndim == 3 and vertices.shape[0] > 1 and vertices.shape[0] * vertices.shape[1] >= 1_000_000:
        # a batch of large meshes: one pose at a time on the shared threads (numpy's loops release
        # the GIL; one pose's temporaries are small enough to be reused rather than freshly
        # mapped); every pose gets the same arithmetic as alone, so the frames are the same bit
        # for bit
        out = np.empty(vertices.shape + (3,), dtype=vertices.dtype)

        def one(i):
            out[i] = local_frames(vertices[i], faces, neighbors, incidence)

        map_blocks(one, range(vertices.shape[0]))
        return out
    n = vertex_normals(vertices, faces, incidence)
    e = vertices[..., neighbors, :] - vertices
    return frames_from_normals(n, e).astype(np.asarray(vertices).dtype, copy=False)


def frames_from_normals(n: np.ndarray, e: np.ndarray) -> np.ndarray:
    """The frames of :func:`local_frames` from unit normals n and the edges e to the frame
    neighbours (both (..., V, 3)): R (..., V, 3, 3), columns t, b, n."""
    t = e - np.einsum("...i,...i->...", e, n)[..., None] * n
    tlen = lengths(t, keepdims=True)
    # an edge parallel to the normal (degenerate) falls back to any perpendicular direction
    parallel = ~(tlen > 1e-6 * np.maximum(lengths(e, keepdims=True), 1e-30))[..., 0]
    wide = np.result_type(t, np.float64)  # the frames are made in double precision from here on
    if t.dtype != wide:
        t = t.astype(wide)
        tlen = lengths(t, keepdims=True)
    if parallel.any():
        alt = cross(n[parallel], np.array([1.0, 0.0, 0.0]))
        short = lengths(alt) < 1e-6
        alt[short] = cross(n[parallel][short], np.array([0.0, 1.0, 0.0]))
        t[parallel] = alt
        tlen[parallel] = lengths(alt, keepdims=True)
    R = np.empty(n.shape + (3,), dtype=np.result_type(n, t))
    R[..., 0] = _normalize(t, fallback=np.array([1.0, 0.0, 0.0]), norm=tlen)
    cross(n, R[..., 0], out=R[..., 1])
    R[..., 2] = n
    return R


def to_local(frames: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """World vectors (..., V, 3) into local frame coordinates: Rᵀ v."""
    return np.einsum("...ji,...j->...i", frames, vectors)


def to_world(frames: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Local frame coordinates (..., V, 3) into world vectors: R v."""
    return np.einsum("...ij,...j->...i", frames, vectors)


@dataclass(frozen=True)
class FramePatch:
    """The faces and vertices that the local frames of a vertex subset depend on, so frames at a
    few vertices of a large mesh cost what the subset costs (validation scores details on an
    evenly spread sample).

    vertices : (n,) the patch's vertices (sorted) — the subset, its faces' corners and frame neighbours;
    faces : (t, 3) every face incident to the subset, in the patch's indices (original order);
    subset : (S,) the subset's positions in ``vertices``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    subset: np.ndarray

    @classmethod
    def around(cls, faces: np.ndarray, n_vertices: int, subset: np.ndarray) -> "FramePatch":
        faces = np.asarray(faces, dtype=np.int64)
        subset = np.asarray(subset, dtype=np.int64)
        incident = np.unique(vertex_face_matrix(faces, n_vertices)[subset].indices)
        patch_faces = faces[incident]
        # every face around a subset vertex is kept, in the original order: its normal sums the same
        # faces in the same order, and its lowest-index neighbour is the same vertex (the map is monotone)
        vertices = np.unique(np.concatenate([patch_faces.ravel(), subset]))
        remap = np.full(n_vertices, -1, dtype=np.int64)
        remap[vertices] = np.arange(len(vertices))
        return cls(vertices, remap[patch_faces], remap[subset])

    def frames(self, positions: np.ndarray) -> np.ndarray:
        """Local frames (..., S, 3, 3) at the subset of full-mesh positions (..., V, 3): the same as
        ``local_frames(positions, faces, frame_neighbors(faces, V))[..., subset, :, :]``."""
        local = positions[..., self.vertices, :]
        out = local_frames(local, self.faces, frame_neighbors(self.faces, len(self.vertices)))
        return out[..., self.subset, :, :]
