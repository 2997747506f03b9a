"""The per-vertex least-squares RBF systems of a growing basis, updated one basis pose at a time.

Learning details from a performance (Bickel et al. 2008, §5.3) fits, per vertex, T training
poses by a basis of P of them in the least-squares sense, and the greedy choice of the basis
refits every vertex at every basis size. Solved afresh each time, a step costs a batched SVD of
(T + 1) × (P + 1) systems and the kernel between every training and basis pose; here the kernel
of each basis pose is computed once, when it joins, and the normal equations are extended by
one row and column, so a step costs a (P + 1) × (P + 1) eigen-decomposition per vertex.

The system and its solution are those of :func:`facepipe.core.psd.solve_rbf` with T > P
(:func:`facepipe.core.psd.constrained_pinv_solve`): rows [Φ s·1] [w; c/s] = D for the training
poses and the side condition s·1ᵀ w = 0, with s the mean |Φ| of the vertex, the rest pose's row
(row 0) met exactly and the others solved by the minimum-norm truncated pseudo-inverse (singular
values at most ``rcond`` × the largest dropped). With the rest row eliminated by the same
Householder reflection H, the reduced system C₁ (rows 1:, columns 1:) has C₁ᵀC₁ = (H G H)₁₁ with
G = the Gram matrix of the other rows, whose eigenvalues are the squared singular values of C₁:
the same cut-off on them is ``rcond²``.
"""

from __future__ import annotations

import numpy as np

from facepipe.parallel import map_blocks, serial_blas


class GrowingRbfSystems:
    """Least-squares RBF systems of every vertex over the same training poses, one column (basis
    pose) added at a time.

    Parameters
    ----------
    targets : (T, V, 3) the training poses' details (row 0: the rest pose).
    max_columns : most basis poses that will be added.
    error_vertices : boolean mask (V,) of the vertices :meth:`solve` measures errors on.
    chunk : vertices per block (the blocks run on the shared threads).

    Memory: the kernel columns, V × T × max_columns floats, and the normal equations.
    """

    def __init__(self, targets: np.ndarray, max_columns: int, error_vertices: np.ndarray, chunk: int = 2048):
        T, V = targets.shape[0], targets.shape[1]
        self.T, self.V, self.chunk = T, V, chunk
        self.targets = np.ascontiguousarray(np.moveaxis(targets, 1, 0), dtype=np.float64)  # (V, T, 3)
        self.phi = np.zeros((V, T, max_columns))
        self.gram = np.zeros((V, max_columns, max_columns))  # Φ[1:]ᵀ Φ[1:]
        self.column_sum = np.zeros((V, max_columns))  # Σ_{r ≥ 1} Φ[r, j]
        self.abs_sum = np.zeros(V)  # Σ |Φ| over every row and column (the scale s)
        self.rhs = np.zeros((V, max_columns, 3))  # Φ[1:]ᵀ D[1:]
        self.target_sum = self.targets[:, 1:].sum(axis=1)  # Σ_{r ≥ 1} D[r]: (V, 3)
        self.error_vertices = np.asarray(error_vertices, dtype=bool)
        self.columns = 0

    def _blocks(self):
        return [slice(s, min(self.V, s + self.chunk)) for s in range(0, self.V, self.chunk)]

    def add_column(self, kernel: np.ndarray) -> None:
        """Append a basis pose: its kernel values φ(r) against every training pose, (V, T)."""
        j = self.columns
        if j >= self.phi.shape[2]:
            raise ValueError(f"the systems were made for {self.phi.shape[2]} columns")

        def block(b):
            k = kernel[b]
            self.phi[b, :, j] = k
            cross = np.einsum("vtp,vt->vp", self.phi[b, 1:, :j + 1], k[:, 1:])
            self.gram[b, :j + 1, j] = cross
            self.gram[b, j, :j + 1] = cross
            self.column_sum[b, j] = k[:, 1:].sum(axis=1)
            self.abs_sum[b] += np.abs(k).sum(axis=1)
            self.rhs[b, j] = np.einsum("vt,vtc->vc", k[:, 1:], self.targets[b, 1:])

        with serial_blas():
            map_blocks(block, self._blocks())
        self.columns = j + 1

    def solve(self, rcond: float, exact: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Weights (V, P, 3), constants (V, 3) and the squared error of every training pose summed
        over the error vertices (T,), for the columns added so far.

        ``exact``: the truncated pseudo-inverse of :func:`~facepipe.core.psd.solve_rbf` (an SVD
        per vertex); else its Tikhonov counterpart (:func:`tikhonov_normal_solve`), a batched LU,
        many times quicker, for scoring a basis while it grows."""
        P = self.columns
        weights = np.empty((self.V, P, 3))
        const = np.empty((self.V, 3))
        blocks = self._blocks()
        squared = np.zeros((len(blocks), self.T))

        def block(i):
            b = blocks[i]
            w, c = self._solve_block(b, P, rcond, exact)
            weights[b], const[b] = w, c
            residual = np.matmul(self.phi[b, :, :P], w) + c[:, None, :] - self.targets[b]  # (n, T, 3)
            mask = self.error_vertices[b]
            squared[i] = np.einsum("vtc,vtc->t", residual[mask], residual[mask])

        with serial_blas():
            map_blocks(block, range(len(blocks)))
        return weights, const, squared.sum(axis=0)

    def _solve_block(self, b: slice, P: int, rcond: float, exact: bool) -> tuple[np.ndarray, np.ndarray]:
        n = self.abs_sum[b].shape[0]
        s = self.abs_sum[b] / (self.T * P)
        s = np.where(s > 0, s, 1.0)
        # the Gram matrix G = MᵀM and Mᵀb of the rows but the rest pose's: training rows 1:, then
        # the side condition's row [s·1ᵀ 0] (right-hand side 0)
        G = np.empty((n, P + 1, P + 1))
        G[:, :P, :P] = self.gram[b, :P, :P] + (s * s)[:, None, None]
        G[:, :P, P] = s[:, None] * self.column_sum[b, :P]
        G[:, P, :P] = G[:, :P, P]
        G[:, P, P] = s * s * (self.T - 1)
        h = np.empty((n, P + 1, 3))
        h[:, :P] = self.rhs[b, :P]
        h[:, P] = s[:, None] * self.target_sum[b]
        # the rest row a₀ = [Φ[0], s], met exactly: H a₀ = −sign·|a₀| e₀ (as constrained_pinv_solve),
        # H = I − t v vᵀ applied as the reflection it is (rank-one updates, not (P+1)³ products)
        a0 = np.concatenate([self.phi[b, 0, :P], s[:, None]], axis=1)
        norm = np.sqrt(np.einsum("np,np->n", a0, a0))
        sign = np.where(a0[:, 0] >= 0, 1.0, -1.0)
        v = a0.copy()
        v[:, 0] += sign * norm
        t = 2.0 / np.einsum("np,np->n", v, v)
        y0 = self.targets[b, 0] / (-sign * norm)[:, None]  # (n, 3)
        Gv = np.einsum("npq,nq->np", G, v)
        vGv = np.einsum("np,np->n", v, Gv)
        # H G H = G − t (v Gvᵀ + Gv vᵀ) + t² (vᵀGv) v vᵀ
        K = G - t[:, None, None] * (v[:, :, None] * Gv[:, None, :] + Gv[:, :, None] * v[:, None, :])
        K += (t * t * vGv)[:, None, None] * (v[:, :, None] * v[:, None, :])
        g = h - t[:, None, None] * v[:, :, None] * np.einsum("np,npc->nc", v, h)[:, None, :]
        rhs1 = g[:, 1:] - K[:, 1:, :1] * y0[:, None, :]
        y1 = (truncated_normal_solve if exact else tikhonov_normal_solve)(np.ascontiguousarray(K[:, 1:, 1:]), rhs1, rcond)
        y = np.concatenate([y0[:, None], y1], axis=1)
        x = y - t[:, None, None] * v[:, :, None] * np.einsum("np,npc->nc", v, y)[:, None, :]
        return x[:, :P], x[:, P] * s[:, None]


def truncated_normal_solve(normal: np.ndarray, rhs: np.ndarray, rcond: float) -> np.ndarray:
    """Minimum-norm least squares of C y = r from its normal equations N y = Cᵀr (N = CᵀC),
    batched (n, k, k), (n, k, m): the singular values of C at most ``rcond`` × the largest are
    dropped (eigenvalues of N at most ``rcond²`` × the largest), as ``pinv(C, rcond) @ r``. By
    the symmetric eigen-decomposition of N (LAPACK's batched ``syevd``: a third quicker than
    an SVD of N on 6 × 6 to 26 × 26 systems). Squaring the condition number costs accuracy
    only for cut-offs far below the default (:data:`facepipe.core.psd.NORMAL_EQUATIONS_MIN_RCOND`)."""
    if normal.shape[1] == 0 or normal.shape[0] == 0:
        return np.zeros(rhs.shape)
    lam, u = np.linalg.eigh(normal)  # ascending: the largest last
    keep = lam > (rcond * rcond) * lam[:, -1:]
    lam_inv = np.divide(1.0, lam, out=np.zeros_like(lam), where=keep)
    return np.matmul(u, lam_inv[:, :, None] * np.matmul(np.swapaxes(u, 1, 2), rhs))


def tikhonov_normal_solve(normal: np.ndarray, rhs: np.ndarray, rcond: float) -> np.ndarray:
    """The Tikhonov counterpart of :func:`truncated_normal_solve`: (N + λI) y = Cᵀr with
    λ = rcond² trace(N) (trace(N) ≥ the largest eigenvalue): directions of C whose singular value
    is well below ``rcond`` × the largest are damped away, the others kept nearly as they are."""
    if normal.shape[1] == 0 or normal.shape[0] == 0:
        return np.zeros(rhs.shape)
    lam = (rcond * rcond) * np.trace(normal, axis1=1, axis2=2)
    lam = np.where(lam > 0, lam, 1.0)
    return np.linalg.solve(normal + lam[:, None, None] * np.eye(normal.shape[1]), rhs)
