"""Large-scale deformation: a linear thin shell constrained at the marker handles.

Bickel et al. 2008, §4: minimise stretch + bending, -k_s Δu + k_b Δ²u = 0, with the
displacements u prescribed at the handle vertices (the markers) and held at zero at
the anchors (skull vertices). The system is linear in the handle displacements, so
the solve is precomputed once as B = -A_ff⁻¹ A_fH and every frame is u = B · u_H.

Discretisation: Δ = M⁻¹ L with the cotangent Laplacian L and the lumped mass M.
Multiplying by M gives the symmetric positive semi-definite operator
A = k_s K + k_b K M⁻¹ K with K = -L.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

# cot(θ) is clamped: a near-degenerate triangle (θ → 0) would otherwise put an
# unbounded weight on one edge and ruin the factorisation's conditioning.
COT_LIMIT = 1e4


def cotmatrix(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Cotangent stiffness matrix K = -L (positive semi-definite, rows sum to zero).

    Parameters
    ----------
    vertices : (V, 3) float, any length unit.
    faces : (T, 3) int triangles.

    Returns
    -------
    K : (V, V) scipy.sparse.csr_matrix float64, dimensionless.
        K_ij = -(cot α_ij + cot β_ij) / 2 for an edge ij, K_ii = -Σ_j K_ij.

    Example
    -------
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.]]); F = np.array([[0, 1, 2]])
    >>> np.allclose(cotmatrix(V, F).sum(axis=1), 0)
    True
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = vertices.shape[0]
    rows, cols, vals = [], [], []
    for k in range(3):
        # the angle at corner k is opposite the edge (i, j)
        i, j, o = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], faces[:, k]
        a = vertices[i] - vertices[o]
        b = vertices[j] - vertices[o]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        dot = np.einsum("ij,ij->i", a, b)
        scale = np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b)
        cot = dot / np.maximum(cross, 1e-12 * scale + 1e-300)
        w = 0.5 * np.clip(cot, -COT_LIMIT, COT_LIMIT)
        rows += [i, j]
        cols += [j, i]
        vals += [-w, -w]
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    vals = np.concatenate(vals)
    off = sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()
    diag = -np.asarray(off.sum(axis=1)).ravel()
    return (off + sp.diags(diag)).tocsr()


def massmatrix(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Lumped (barycentric) vertex areas: a third of the area of each incident triangle.

    Barycentric lumping stays positive on obtuse triangles, where the Voronoi areas
    of the mixed scheme need special cases.

    Parameters
    ----------
    vertices : (V, 3) float; faces : (T, 3) int.

    Returns
    -------
    mass : (V,) float64 in length² units, floored at a tiny fraction of the mean so
        that a vertex only touched by degenerate triangles does not divide by zero.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    area = 0.5 * np.linalg.norm(
        np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1
    )
    mass = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=vertices.shape[0])
    floor = 1e-8 * max(float(mass.mean()), 1e-300)
    return np.maximum(mass, floor)


def marker_spacing(vertices: np.ndarray, handles: np.ndarray) -> float:
    """Mean distance from each handle to its nearest other handle (length units)."""
    from scipy.spatial import cKDTree

    points = np.asarray(vertices, dtype=np.float64)[np.asarray(handles)]
    if len(points) < 2:
        return 1.0
    dist, _ = cKDTree(points).query(points, k=2)
    return float(dist[:, 1].mean())


def shell_operator(vertices: np.ndarray, faces: np.ndarray, k_stretch: float, k_bend: float,
                   spacing: float = 1.0) -> sp.csr_matrix:
    """The symmetric shell operator A = (k_stretch / h²) K + k_bend K M⁻¹ K.

    ``k_stretch`` is relative to the marker spacing ``h``: K M⁻¹ K scales as 1/length²
    while K is scale-free, so dividing k_stretch by h² makes the same value mean the
    same trade-off on any mesh size and marker density.

    Returns
    -------
    A : (V, V) csr_matrix float64.
    """
    K = cotmatrix(vertices, faces)
    A = sp.csr_matrix(K.shape)
    if k_bend:
        Minv = sp.diags(1.0 / massmatrix(vertices, faces))
        A = A + k_bend * (K @ Minv @ K)
    if k_stretch:
        A = A + (k_stretch / spacing**2) * K
    return A.tocsr()


class CholeskyFactor:
    """A sparse Cholesky factorisation of a symmetric positive definite matrix.

    CHOLMOD (through cholespy, which ships it in a wheel) is used when installed;
    SciPy's SuperLU is the fallback. ``solve`` takes one or many right-hand sides.
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        self.backend = "cholmod"
        try:
            import cholespy

            coo = A.tocoo()
            self._solver = cholespy.CholeskySolverD(
                self.n,
                coo.row.astype(np.int32),
                coo.col.astype(np.int32),
                coo.data.astype(np.float64),
                cholespy.MatrixType.COO,
            )
        except ImportError:
            import scipy.sparse.linalg as spla

            self.backend = "superlu"
            self._solver = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self.backend == "superlu":
            return self._solver.solve(b)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x


def constrained_split(n_vertices: int, handles: np.ndarray, anchors: np.ndarray | None):
    """Indices of the free vertices and a boolean mask of the constrained ones."""
    constrained = np.zeros(n_vertices, dtype=bool)
    constrained[np.asarray(handles, dtype=np.int64)] = True
    if anchors is not None and len(anchors):
        constrained[np.asarray(anchors, dtype=np.int64)] = True
    return np.flatnonzero(~constrained), constrained


def shell_basis(vertices: np.ndarray, faces: np.ndarray, handles: np.ndarray, anchors: np.ndarray | None = None,
                k_stretch: float = 0.0, k_bend: float = 1.0, spacing: float | None = None,
                columns: np.ndarray | None = None) -> np.ndarray:
    """The large-scale basis B: displacements u = B · u_H for handle displacements u_H.

    Parameters
    ----------
    vertices : (V, 3) rest positions; faces : (T, 3) triangles.
    handles : (H,) int vertex indices whose displacement is prescribed.
    anchors : (A,) int vertex indices held at zero displacement, or None.
    k_stretch, k_bend : shell stiffnesses; k_stretch relative to the marker spacing.
    spacing : marker spacing h (length units); default: mean nearest-handle distance.
    columns : optional (A,) extra prescribed vertices to return columns for
        (normally the anchors, whose displacement is zero so their columns are unused).

    Returns
    -------
    B : (V, H) float64 (or (V, H + len(columns))) — rows of handles are unit rows.
        Without anchors, every row sums to 1: a rigid translation is reproduced.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    handles = np.asarray(handles, dtype=np.int64)
    n = vertices.shape[0]
    if spacing is None:
        spacing = marker_spacing(vertices, handles)
    A = shell_operator(vertices, faces, k_stretch, k_bend, spacing)
    free, _ = constrained_split(n, handles, anchors)
    driven = handles if columns is None else np.concatenate([handles, np.asarray(columns, dtype=np.int64)])
    A = A.tocsc()
    A_ff = A[free][:, free]
    A_fh = A[free][:, driven]
    B = np.zeros((n, len(driven)), dtype=np.float64)
    B[driven, np.arange(len(driven))] = 1.0
    if len(free):
        B[free] = -CholeskyFactor(A_ff).solve(A_fh.toarray())
    return B


def large_scale_positions(rest: np.ndarray, B: np.ndarray, handle_displacements: np.ndarray) -> np.ndarray:
    """Rest positions plus B · u_H, batched over frames.

    Parameters
    ----------
    rest : (V, 3); B : (V, H); handle_displacements : (..., H, 3).

    Returns
    -------
    (..., V, 3) positions, in the dtype of B.
    """
    u = np.einsum("vh,...hc->...vc", B, handle_displacements.astype(B.dtype, copy=False), optimize=True)
    return u + rest.astype(B.dtype, copy=False)
