"""Local strain of a deformed surface relative to its rest pose, per vertex, rigid-invariant.

Bickel et al. 2008 (§5.1) note that a per-vertex strain tensor could replace the feature-edge
strain. Per triangle, the deformation gradient in the rest triangle's plane, F = D_s D_m⁻¹
(3 × 2: D_m the rest edges in an orthonormal in-plane frame, D_s the deformed edges in 3D),
gives the Green strain E = ½ (FᵀF − I), a symmetric 2 × 2 tensor in that rest frame. It does not
change under any rigid motion of the deformed triangle, so neither does anything built from it.
Each triangle's tensor is written as a 3 × 3 tensor of the rest space (A E Aᵀ, A the frame's two
axes), summed onto the vertices weighted by rest area, and read in each vertex's rest tangent
frame (t, b): three numbers per vertex,

    (E_tt, E_bb, √2 E_tb),

scaled so that their Euclidean distance is the Frobenius distance of the tensors (the same for
any choice of t within the tangent plane). Compression is negative; strain has no unit, so
widths and thresholds over it suit any face at any scale.

Everything is arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from facepipe.core.tangent_frames import frame_neighbors, local_frames, vertex_face_matrix

SQRT2 = float(np.sqrt(2.0))


@dataclass(frozen=True)
class StrainOperator:
    """The rest-pose quantities of :func:`vertex_strain`, computed once per mesh.

    faces : (T, 3) int64.
    inverse_rest_edges : (T, 2, 2) D_m⁻¹ of every triangle (zero for degenerate triangles).
    projection : (T, 2, 3) the rest frame's axes Aᵀ of every triangle (rows).
    gather : (V, T) sparse, the rest area of each incident triangle over the vertex's total.
    tangents : (V, 3, 2) each vertex's rest tangent axes (t, b) as columns.
    """

    faces: np.ndarray
    inverse_rest_edges: np.ndarray
    projection: np.ndarray
    gather: sp.csr_matrix
    tangents: np.ndarray

    @classmethod
    def of(cls, rest: np.ndarray, faces: np.ndarray, neighbors: np.ndarray | None = None) -> "StrainOperator":
        rest = np.asarray(rest, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        V = rest.shape[0]
        e1 = rest[faces[:, 1]] - rest[faces[:, 0]]
        e2 = rest[faces[:, 2]] - rest[faces[:, 0]]
        normal = np.cross(e1, e2)
        double_area = np.linalg.norm(normal, axis=1)
        len1 = np.linalg.norm(e1, axis=1)
        good = (double_area > 1e-12 * np.maximum(len1, 1e-300) ** 2) & (len1 > 0)
        a = e1 / np.where(good, len1, 1.0)[:, None]
        n = normal / np.where(good, double_area, 1.0)[:, None]
        b = np.cross(n, a)
        # D_m = [[a·e1, a·e2], [b·e1, b·e2]] = [[|e1|, a·e2], [0, b·e2]]: upper triangular
        m11, m12, m22 = len1, np.einsum("ti,ti->t", a, e2), np.einsum("ti,ti->t", b, e2)
        inverse = np.zeros((len(faces), 2, 2))
        ok = good & (np.abs(m22) > 0)
        inverse[ok, 0, 0] = 1.0 / m11[ok]
        inverse[ok, 0, 1] = -m12[ok] / (m11[ok] * m22[ok])
        inverse[ok, 1, 1] = 1.0 / m22[ok]
        projection = np.stack([a, b], axis=1) * ok[:, None, None]
        area = 0.5 * double_area * ok
        incidence = vertex_face_matrix(faces, V)
        total = np.asarray(incidence @ area).ravel()
        scale = sp.diags(1.0 / np.where(total > 0, total, 1.0))
        gather = (scale @ incidence @ sp.diags(area)).tocsr()
        if neighbors is None:
            neighbors = frame_neighbors(faces, V)
        frames = local_frames(rest, faces, neighbors, incidence)
        return cls(faces, inverse, projection, gather, np.ascontiguousarray(frames[:, :, :2]))

    @property
    def n_vertices(self) -> int:
        return self.gather.shape[0]


def triangle_green_strain(positions: np.ndarray, op: StrainOperator) -> np.ndarray:
    """Green strain ½ (FᵀF − I) of every triangle in its rest frame: (..., V, 3) → (..., T, 2, 2)."""
    p = np.asarray(positions)
    f = op.faces
    p0 = p[..., f[:, 0], :]
    Ds = np.stack([p[..., f[:, 1], :] - p0, p[..., f[:, 2], :] - p0], axis=-1)  # (..., T, 3, 2)
    F = Ds @ op.inverse_rest_edges
    C = np.swapaxes(F, -1, -2) @ F
    eye = np.eye(2) * (np.abs(op.inverse_rest_edges).sum(axis=(-1, -2)) > 0)[:, None, None]
    return 0.5 * (C - eye)


def vertex_strain(positions: np.ndarray, op: StrainOperator) -> np.ndarray:
    """Per-vertex strain (E_tt, E_bb, √2 E_tb) in the rest tangent frames: (..., V, 3) → (..., V, 3).

    The triangles' tensors, as 3 × 3 tensors of the rest space, are averaged over each vertex's
    incident triangles by rest area and read in the vertex's rest tangent axes."""
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim == 3 and positions.shape[0] > 1 and positions.shape[0] * op.faces.shape[0] >= 1_000_000:
        # a batch of large meshes one pose at a time: the (T, 3, 3) temporaries of a whole batch
        # would take gigabytes; each pose gets the same arithmetic as alone
        return np.stack([vertex_strain(p, op) for p in positions])
    lead = positions.shape[:-2]
    E = triangle_green_strain(positions, op)  # (..., T, 2, 2)
    A = op.projection  # (T, 2, 3)
    E3 = np.swapaxes(A, -1, -2) @ E @ A  # (..., T, 3, 3)
    T = A.shape[0]
    upper = E3[..., [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]  # (..., T, 6)
    flat = np.moveaxis(upper, -2, 0).reshape(T, -1)
    Ev = np.asarray(op.gather @ flat).reshape((op.n_vertices,) + lead + (6,))
    Ev = np.moveaxis(Ev, 0, -2)  # (..., V, 6)
    full = Ev[..., [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(Ev.shape[:-1] + (3, 3))
    t, b = op.tangents[..., 0], op.tangents[..., 1]  # (V, 3)
    Et = np.einsum("...vij,vj->...vi", full, t)
    Eb = np.einsum("...vij,vj->...vi", full, b)
    return np.stack([np.einsum("...vi,vi->...v", Et, t), np.einsum("...vi,vi->...v", Eb, b),
                     SQRT2 * np.einsum("...vi,vi->...v", Et, b)], axis=-1)


def principal_strains(strain: np.ndarray) -> np.ndarray:
    """The two principal strains (smallest first) of per-vertex strains (..., 3) from :func:`vertex_strain`."""
    s = np.asarray(strain)
    mean = 0.5 * (s[..., 0] + s[..., 1])
    radius = np.sqrt(0.25 * (s[..., 0] - s[..., 1]) ** 2 + 0.5 * s[..., 2] ** 2)
    return np.stack([mean - radius, mean + radius], axis=-1)


def ring_strain_coefficients(rest: np.ndarray, op: StrainOperator) -> tuple[np.ndarray, np.ndarray]:
    """:func:`vertex_strain` as a sum over each vertex's ring of faces, for kernels that gather
    per vertex (no scatter): the strain at v is linear in the Gram matrices of its faces' edges
    from v, G = [[a·a, a·b], [a·b, b·b]] (a, b the deformed edges from v to the face's other two
    corners, in the face's own winding), so

        s_v,k = const_v,k + Σ_faces (coeff_k,0 a·a + coeff_k,1 a·b + coeff_k,2 b·b).

    The ring entries are in the order of
    :func:`facepipe.opencl.engine.vertex_face_ring` (by vertex, then face index).

    Returns
    -------
    coeff : (3T, 3, 3) float64, entry × strain component (tt, bb, √2 tb) × (aa, ab, bb);
    const : (V, 3) float64.
    """
    rest = np.asarray(rest, dtype=np.float64)
    faces = op.faces
    V = op.n_vertices
    corner_vertex = faces.ravel()
    order = np.argsort(corner_vertex, kind="stable")
    face = order // 3
    corner = order % 3
    v = corner_vertex[order]
    a = faces[face, (corner + 1) % 3]
    b = faces[face, (corner + 2) % 3]
    A = op.projection[face]  # (n, 2, 3), zero for degenerate faces
    ea = np.einsum("nij,nj->ni", A, rest[a] - rest[v])
    eb = np.einsum("nij,nj->ni", A, rest[b] - rest[v])
    Dm = np.stack([ea, eb], axis=-1)  # (n, 2, 2), columns: the rest edges in the face's frame
    det = Dm[:, 0, 0] * Dm[:, 1, 1] - Dm[:, 0, 1] * Dm[:, 1, 0]
    ok = np.abs(det) > 0
    inv = np.zeros_like(Dm)
    safe = np.where(ok, det, 1.0)
    inv[:, 0, 0], inv[:, 1, 1] = Dm[:, 1, 1] / safe, Dm[:, 0, 0] / safe
    inv[:, 0, 1], inv[:, 1, 0] = -Dm[:, 0, 1] / safe, -Dm[:, 1, 0] / safe
    w = np.asarray(op.gather[v, face]).ravel() * ok
    pt = np.einsum("nij,nj->ni", A, op.tangents[v, :, 0])
    pb = np.einsum("nij,nj->ni", A, op.tangents[v, :, 1])
    u = np.einsum("nij,nj->ni", inv, pt)
    z = np.einsum("nij,nj->ni", inv, pb)
    half = 0.5 * w
    coeff = np.empty((len(order), 3, 3))
    coeff[:, 0] = half[:, None] * np.stack([u[:, 0] ** 2, 2 * u[:, 0] * u[:, 1], u[:, 1] ** 2], -1)
    coeff[:, 1] = half[:, None] * np.stack([z[:, 0] ** 2, 2 * z[:, 0] * z[:, 1], z[:, 1] ** 2], -1)
    coeff[:, 2] = (SQRT2 * half)[:, None] * np.stack([u[:, 0] * z[:, 0], u[:, 0] * z[:, 1] + u[:, 1] * z[:, 0],
                                                      u[:, 1] * z[:, 1]], -1)
    const = np.zeros((V, 3))
    np.add.at(const, v, -half[:, None] * np.stack([np.einsum("ni,ni->n", pt, pt), np.einsum("ni,ni->n", pb, pb),
                                                   SQRT2 * np.einsum("ni,ni->n", pt, pb)], -1))
    return coeff, const


def ring_vertex_strain(positions: np.ndarray, faces: np.ndarray, coeff: np.ndarray, const: np.ndarray) -> np.ndarray:
    """:func:`vertex_strain` from :func:`ring_strain_coefficients` (a second implementation, the
    kernels' arithmetic): positions (..., V, 3) → (..., V, 3)."""
    p = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    corner_vertex = faces.ravel()
    order = np.argsort(corner_vertex, kind="stable")
    face, corner = order // 3, order % 3
    v = corner_vertex[order]
    ea = p[..., faces[face, (corner + 1) % 3], :] - p[..., v, :]
    eb = p[..., faces[face, (corner + 2) % 3], :] - p[..., v, :]
    gram = np.stack([np.einsum("...i,...i->...", ea, ea), np.einsum("...i,...i->...", ea, eb),
                     np.einsum("...i,...i->...", eb, eb)], -1)  # (..., n, 3)
    terms = np.einsum("nkg,...ng->...nk", coeff, gram)  # (..., n, 3)
    gather = sp.csr_matrix((np.ones(len(v)), (v, np.arange(len(v)))), shape=(const.shape[0], len(v)))
    lead = terms.shape[:-2]
    summed = np.asarray(gather @ np.moveaxis(terms, -2, 0).reshape(len(v), -1)).reshape((const.shape[0],) + lead + (3,))
    return np.moveaxis(summed, 0, -2) + const
