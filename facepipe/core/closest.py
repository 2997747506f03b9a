"""Closest points on a triangle mesh, preferring triangles that face the query's way.

Used to put one surface in correspondence with another (detail transfer, non-rigid refinement):
a vertex is mapped to the nearest point of the other mesh whose triangle faces its way, so the
upper lip's underside is not mapped onto the lower lip's top.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from trimesh.triangles import closest_point, points_to_barycentric

from facepipe.core.runs import offsets_within
from facepipe.core.tangent_frames import vertex_face_matrix

__all__ = ["MIN_NORMAL_COS", "closest_point_on_triangles", "project_points"]

# a triangle faces a point's way when their normals are within 60°
MIN_NORMAL_COS = 0.5


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest point of triangles (a, b, c) to points p.

    Parameters
    ----------
    p, a, b, c : (..., 3) broadcastable.

    Returns
    -------
    (..., 3) barycentric weights (≥ 0, sum 1) of the closest point: q = w0 a + w1 b + w2 c.
    """
    p, a, b, c = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (p, a, b, c)))
    shape = p.shape
    tri = np.stack([a, b, c], axis=-2).reshape(-1, 3, 3)
    q = closest_point(tri, p.reshape(-1, 3))
    with np.errstate(all="ignore"):
        bary = points_to_barycentric(tri, q)
    # degenerate (zero-area) triangles give NaN: their centroid stands in, as good as any point
    bary = np.clip(np.nan_to_num(bary, nan=1.0 / 3.0), 0.0, 1.0)
    return (bary / bary.sum(axis=-1, keepdims=True)).reshape(shape)


def _incident_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, K) the faces around every vertex, padded with −1."""
    inc = vertex_face_matrix(faces, n_vertices).tocsr()
    counts = np.diff(inc.indptr)
    out = np.full((n_vertices, max(int(counts.max(initial=0)), 1)), -1, dtype=np.int64)
    rows = np.repeat(np.arange(n_vertices), counts)
    cols = offsets_within(counts)
    out[rows, cols] = inc.indices
    return out


def project_points(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                   min_cos: float = MIN_NORMAL_COS, neighbours: int = 8, chunk: int = 8192):
    """Closest points of a triangle mesh to query points, preferring triangles that face their way.

    Candidates are the triangles around the ``neighbours`` nearest mesh vertices and the
    ``neighbours`` triangles with the nearest centroids; among them the nearest whose normal is
    within acos(min_cos) of the query's normal wins (the upper lip's underside is not mapped to
    the lower lip's top), else the nearest of all, flagged.

    Parameters
    ----------
    points, normals : (N, 3) query points and their unit normals.
    vertices : (V, 3); faces : (T, 3) the mesh projected onto.

    Returns
    -------
    face : (N,) int64 triangle; bary : (N, 3) barycentric weights; distance : (N,);
    normal_ok : (N,) bool, whether the chosen triangle faces the query's way.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    around = _incident_faces(faces, len(vertices))
    kv = min(neighbours, len(vertices))
    kc = min(neighbours, len(faces))
    vtree = cKDTree(vertices)
    ctree = cKDTree(tri.mean(axis=1))
    N = len(points)
    face = np.empty(N, dtype=np.int64)
    bary = np.empty((N, 3))
    dist = np.empty(N)
    ok = np.empty(N, dtype=bool)
    for s in range(0, N, chunk):
        p = np.asarray(points[s:s + chunk], dtype=np.float64)
        n = np.asarray(normals[s:s + chunk], dtype=np.float64)
        _, iv = vtree.query(p, k=kv)
        _, ic = ctree.query(p, k=kc)
        iv, ic = iv.reshape(len(p), kv), ic.reshape(len(p), kc)
        cand = np.concatenate([around[iv].reshape(len(p), -1), ic], axis=1)  # (n, C), −1 = none
        valid = cand >= 0
        c = np.where(valid, cand, 0)
        t = tri[c]  # (n, C, 3, 3)
        w = closest_point_on_triangles(p[:, None], t[..., 0, :], t[..., 1, :], t[..., 2, :])
        q = np.einsum("ncj,ncjx->ncx", w, t)
        d = np.linalg.norm(q - p[:, None], axis=-1)
        d = np.where(valid, d, np.inf)
        agree = np.einsum("nx,ncx->nc", n, fn[c]) >= min_cos
        d_ok = np.where(agree, d, np.inf)
        best_ok = np.argmin(d_ok, axis=1)
        found = np.isfinite(d_ok[np.arange(len(p)), best_ok])
        best = np.where(found, best_ok, np.argmin(d, axis=1))
        r = np.arange(len(p))
        face[s:s + chunk] = c[r, best]
        bary[s:s + chunk] = w[r, best]
        dist[s:s + chunk] = d[r, best]
        ok[s:s + chunk] = found
    return face, bary, dist, ok
