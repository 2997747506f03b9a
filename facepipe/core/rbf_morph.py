"""RBF volume morphing: an alternative large-scale deformer (Fidaleo et al. 2000).

The displacement of every point x is an interpolant of the marker displacements,

    u(x) = Σ_j a_j h_j(|x − c_j|) + A x + b,     h_j(r) = √(r² + s_j²)  (Hardy multiquadric)

over centres c_j = the markers plus *phantom points* held at zero displacement (the skull
anchors, or points around the face's border) so that the morph fades out where the face
meets the head. s_j is the distance from centre j to its nearest other centre (Eck), the
affine term reproduces rigid and affine motion exactly, and a Tikhonov term λ on the
diagonal smooths noisy markers. The multiquadric is conditionally negative definite, so the
term is subtracted (Φ − λI): adding it can make the system singular. The solve is linear in the marker displacements, so it is
precomputed into the same B matrix as the shell: u = B · u_H. No mesh connectivity is
needed: meshes with several components (eyes, teeth) deform too.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from facepipe.errors import InputError


def farthest_point_subset(points: np.ndarray, count: int, seed_index: int = 0) -> np.ndarray:
    """Indices of ``count`` points spread out by farthest-point sampling (deterministic)."""
    n = len(points)
    if count >= n:
        return np.arange(n)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = seed_index
    dist = np.linalg.norm(points - points[seed_index], axis=1)
    for k in range(1, count):
        chosen[k] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[k]], axis=1))
    return chosen


def boundary_vertices(faces: np.ndarray) -> np.ndarray:
    """Vertices on open boundary edges (edges used by one triangle)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return np.unique(uniq[counts == 1])


def phantom_points(vertices: np.ndarray, faces: np.ndarray | None, anchors: np.ndarray, handles: np.ndarray,
                   max_count: int | None = None) -> np.ndarray:
    """Vertex indices of phantom points: the anchors, else the mesh border, spread out.

    The outer border of a face mesh is where it meets the rest of the head; the border vertices
    nearer to a marker than the marker spacing (lips, eyelids: inner borders) are left out,
    since the markers there drive them.
    """
    handles = np.asarray(handles, dtype=np.int64)
    max_count = max_count or 2 * len(handles)
    if len(anchors):
        candidates = np.asarray(anchors, dtype=np.int64)
    elif faces is not None:
        candidates = boundary_vertices(faces)
        tree = cKDTree(vertices[handles])
        spacing = np.median(tree.query(vertices[handles], k=2)[0][:, 1])
        candidates = candidates[tree.query(vertices[candidates])[0] > 1.5 * spacing]
    else:
        candidates = np.zeros(0, dtype=np.int64)
    candidates = np.setdiff1d(candidates, handles)
    if len(candidates) == 0:
        return candidates
    pick = farthest_point_subset(vertices[candidates], min(max_count, len(candidates)))
    return np.sort(candidates[pick])


def multiquadric_basis(vertices: np.ndarray, handles: np.ndarray, phantoms: np.ndarray,
                       regularization: float = 0.01, chunk: int = 65536) -> np.ndarray:
    """The RBF volume morph as a large-scale basis B (V, H).

    Parameters
    ----------
    vertices : (V, 3) rest positions (length units).
    handles : (H,) vertex indices of the markers; phantoms : (A,) vertex indices held at zero.
    regularization : Tikhonov λ relative to the median centre spacing (dimensionless), so the
        same value smooths alike on any scale; 0 interpolates the markers exactly.

    Returns
    -------
    B : (V, H) float64 with u = B · u_H. Rows sum to 1 when there are no phantoms (the affine
        term reproduces a translation).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    centres_idx = np.concatenate([np.asarray(handles, np.int64), np.asarray(phantoms, np.int64)])
    C = vertices[centres_idx]
    N, H = len(C), len(handles)
    if N < 4:
        raise InputError(f"the RBF morph needs at least 4 markers and phantom points, has {N}")
    d, _ = cKDTree(C).query(C, k=2)
    s = d[:, 1]
    if (s <= 0).any():
        raise InputError("two RBF centres (markers or phantom points) coincide",
                         hint="check markers.csv and anchors.txt for duplicate vertices")
    lam = regularization * float(np.median(s))
    r = np.linalg.norm(C[:, None] - C[None], axis=-1)
    Phi = np.sqrt(r**2 + s[None, :] ** 2)
    P = np.hstack([C, np.ones((N, 1))])
    K = np.zeros((N + 4, N + 4))
    K[:N, :N] = Phi - lam * np.eye(N)
    K[:N, N:] = P
    K[N:, :N] = P.T
    # coefficients for unit displacement of each handle (phantoms stay at zero)
    rhs = np.zeros((N + 4, H))
    rhs[np.arange(H), np.arange(H)] = 1.0
    coef = np.linalg.solve(K, rhs)  # (N + 4, H)
    B = np.empty((len(vertices), H))
    for start in range(0, len(vertices), chunk):
        x = vertices[start:start + chunk]
        rx = np.linalg.norm(x[:, None] - C[None], axis=-1)
        kx = np.hstack([np.sqrt(rx**2 + s[None, :] ** 2), x, np.ones((len(x), 1))])
        B[start:start + chunk] = kx @ coef
    return B
