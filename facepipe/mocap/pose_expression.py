"""Head pose and expression weights of each frame's markers, fitted together.

A frame's markers are a rigid head motion of an expression in the span of the rig's examples:
x_fm = R_f (r_m + Σ_k c_fk D_km) + t_f, with r the neutral handles and D_k the examples' handle
displacements. :func:`fit_pose_expression` fits R_f, t_f and the weights c ≥ 0 by Gauss–Newton,
each step a projected Newton step over the weights held at zero (an active set), optionally with
an L1 prior on c and Huber reweighting of jumping markers. Frames are independent and fitted in
batches. Pure functions over arrays (:mod:`facepipe.mocap.cleaning` builds on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facepipe.core.rigid import rotation_from_vector

__all__ = ["fit_pose_expression", "CONVERGED_STEP"]


def _skew(q: np.ndarray) -> np.ndarray:
    K = np.zeros(q.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -q[..., 2], q[..., 1], -q[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = q[..., 2], -q[..., 1], q[..., 0]
    return K


def fit_pose_expression(world: np.ndarray, weights: np.ndarray, reference: np.ndarray, basis: np.ndarray,
                        R: np.ndarray, t: np.ndarray, coeffs: np.ndarray | None = None,
                        l1: np.ndarray | None = None, iterations: int = 12, fix_pose: bool = False,
                        robust_scale: np.ndarray | None = None, active: np.ndarray | None = None,
                        chunk: int = 256):
    """Fit head pose and non-negative expression weights to each frame's markers.

    Minimises, per frame f, Σ_m w_fm |R_f (r_m + Σ_k c_k D_km) + t_f − x_fm|² + Σ_k l1_fk c_k
    over R_f, t_f and c ≥ 0 by Gauss–Newton; each step solves the linearised problem with
    the weights at zero held as an active set (projected Newton): a weight that would turn
    negative stops at zero and leaves the set, one whose gradient asks for it comes back.

    Parameters
    ----------
    world : (T, H, 3) markers, NaN where missing (their weight must be 0).
    weights : (T, H) ≥ 0 per-sample weights (inverse variances).
    reference : (H, 3) neutral handles r (head space).
    basis : (K, H, 3) example displacements D (K may be 0).
    R, t : (T, 3, 3), (T, 3) starting pose (world = R @ head + t).
    coeffs : (T, K) starting weights, default 0.
    l1 : (T, K) ≥ 0 L1 weights (0: plain non-negative least squares).
    iterations : Gauss–Newton steps.
    fix_pose : keep R, t as given (fit the expression only).
    active : (T, K) bool, optional
        Only these weights may be non-zero (the others are held at zero): a refit on a
        support chosen with the L1 prior, without its shrinkage (the "relaxed lasso").
    robust_scale : (H,) or scalar residual scale; when given, samples are reweighted each
        step by min(1, c / u), u = residual / scale, c = 3 × max(1, the frame's median u)
        (Huber), so a jumping marker pulls less.

    Returns
    -------
    R : (T, 3, 3); t : (T, 3); coeffs : (T, K); w : (T, H) the weights used last.
    """
    T = world.shape[0]
    K = basis.shape[0]
    R = np.array(R, dtype=np.float64)
    t = np.array(t, dtype=np.float64)
    C = np.zeros((T, K)) if coeffs is None else np.maximum(np.array(coeffs, dtype=np.float64), 0.0)
    l1 = np.zeros((T, K)) if l1 is None else np.asarray(l1, dtype=np.float64)
    x = np.where(np.isfinite(world), world, 0.0)
    w_all = np.asarray(weights, dtype=np.float64).copy()
    out_w = w_all.copy()
    expression = _ExpressionBasis.of(reference, basis)
    for a in range(0, T, chunk):  # frames in chunks: the normal equations are (chunk, 6 + K, 6 + K)
        b = min(T, a + chunk)
        allowed = np.ones((b - a, K), dtype=bool) if active is None else np.asarray(active[a:b], dtype=bool)
        R[a:b], t[a:b], C[a:b], out_w[a:b] = _fit_frames(
            x[a:b], w_all[a:b], R[a:b], t[a:b], C[a:b], l1[a:b], allowed, expression, iterations, fix_pose,
            robust_scale)
    return R, t, C, out_w


@dataclass(frozen=True)
class _ExpressionBasis:
    """The neutral handles and the examples' displacements, in the layouts the normal equations use."""

    reference: np.ndarray  # (H, 3) r
    D: np.ndarray  # (H, 3, K) D_km by marker
    Dflat: np.ndarray  # (3H, K)
    DtD: np.ndarray  # (H, K²) per marker D_mᵀ D_m

    @classmethod
    def of(cls, reference: np.ndarray, basis: np.ndarray) -> "_ExpressionBasis":
        H, K = basis.shape[1], basis.shape[0]
        D = basis.transpose(1, 2, 0)
        return cls(reference, D, D.reshape(H * 3, K), np.einsum("hak,hal->hkl", D, D).reshape(H, K * K))

    @property
    def K(self) -> int:
        return self.D.shape[2]

    def handles(self, C: np.ndarray) -> np.ndarray:
        """(n, H, 3) the head-space handles r + Σ_k c_k D_k of weights C (n, K)."""
        return self.reference + (C @ self.Dflat.T).reshape(len(C), len(self.reference), 3)


# A frame's Gauss–Newton stops once a step moves its weights and rotation (radians) by at most this,
# and its translation by at most this times the handles' spread: the steps left would change
# nothing a replay can show, and most frames get there in a few of the allowed iterations
CONVERGED_STEP = 1e-12


def _fit_frames(x, w0, R, t, C, l1, allowed, expression: _ExpressionBasis, iterations: int, fix_pose: bool,
                robust_scale):
    """Gauss–Newton of :func:`fit_pose_expression` on a chunk of frames: x (n, H, 3) markers (0 where
    missing), w0 (n, H) their weights, R, t, C the starting pose and weights, l1 (n, K), allowed
    (n, K) the weights that may be non-zero. Returns R, t, C and the sample weights used last.

    Each frame iterates until its step is below :data:`CONVERGED_STEP` or ``iterations`` are
    done; the frames still iterating are solved together (what a frame gets does not depend on
    the others in the chunk)."""
    K = expression.K
    n_pose = 0 if fix_pose else 6
    R, t = np.array(R, dtype=np.float64), np.array(t, dtype=np.float64)
    C = np.where(allowed, C, 0.0)
    free = allowed.copy()
    w_out = np.array(w0, dtype=np.float64)
    spread = float(np.sqrt(((expression.reference - expression.reference.mean(axis=0)) ** 2).sum(axis=1).mean()))
    going = np.arange(len(C))  # the frames still iterating
    for _ in range(iterations):
        if not going.size:
            break
        part = slice(None) if going.size == len(C) else going
        Rg, tg, Cg, fg, xg, w0g = R[part], t[part], C[part], free[part], x[part], w0[part]
        y = expression.handles(Cg)
        q = np.einsum("nij,nhj->nhi", Rg, y)
        r = xg - (q + tg[:, None, :])
        w = _huber_weights(w0g, r, robust_scale) if robust_scale is not None else w0g
        A, g = _normal_equations(Rg, y, q, r, w, expression, fix_pose)
        if K:
            g[:, n_pose:] -= l1[part]
            # weights at zero whose gradient points inward come back into the set
            fg = (fg | ((Cg <= 0) & (g[:, n_pose:] > 0) & allowed[part])) & ((Cg > 0) | (g[:, n_pose:] > 0))
        _regularise(A, n_pose, K, fix_pose)
        step, fg = _solve_active_set(A, g, Cg, fg, n_pose, K)
        alpha = np.ones(len(Cg))
        if K:
            alpha, Cg, fg = _step_weights(Cg, step[:, n_pose:], fg)
        taken = alpha[:, None] * step
        if not fix_pose:
            R[part] = rotation_from_vector(taken[:, :3]) @ Rg
            t[part] = tg + taken[:, 3:6]
            taken[:, 3:6] /= max(spread, 1e-300)
        C[part], free[part], w_out[part] = Cg, fg, w
        going = going[np.abs(taken).max(axis=1, initial=0.0) > CONVERGED_STEP]
    return R, t, C, w_out


def _huber_weights(w0: np.ndarray, r: np.ndarray, robust_scale) -> np.ndarray:
    """Sample weights w0 reweighted by the residuals r (n, H, 3) in units of each marker's scale.

    Huber weights, with the frame's own robust scale as the floor: a jumping marker pulls less on
    pose and weights. Huber, not a redescending (Cauchy, Tukey) loss: the problem stays convex,
    so markers showing an expression the examples lack are not talked away.
    """
    u = np.linalg.norm(r, axis=-1) / robust_scale
    seen = w0 > 0
    # a frame without a seen marker has no median: 0 stands in for it (c is then the floor)
    med = np.nanmedian(np.where(seen, u, np.where(seen.any(axis=1, keepdims=True), np.nan, 0.0)), axis=1,
                       keepdims=True)
    c = 3.0 * np.maximum(np.nan_to_num(med, nan=1.0), 1.0)
    return w0 * np.minimum(1.0, c / np.maximum(u, 1e-300))


def _normal_equations(R, y, q, r, w, expression: _ExpressionBasis, fix_pose: bool):
    """A δ = g of the problem linearised at pose R and handles y (q = R y, r the residuals): (n, P, P)
    and (n, P), P = 6 + K (rotation vector, translation, weights; K without the pose).

    Assembled from sums over markers (J = [-[q]×, I, R D_m] is never formed): BLAS-sized products only.
    """
    n, H, _ = y.shape
    K = expression.K
    D = expression.D
    n_pose = 0 if fix_pose else 6
    P = n_pose + K
    eye3 = np.eye(3)
    A = np.zeros((n, P, P))
    g = np.zeros((n, P))
    wr = w[..., None] * r
    if not fix_pose:
        wq = w[..., None] * q
        sw = w.sum(axis=1)
        qq = np.einsum("nhi,nhj->nij", wq, q)
        A[:, 0:3, 0:3] = np.trace(qq, axis1=1, axis2=2)[:, None, None] * eye3 - qq
        A[:, 0:3, 3:6] = _skew(wq.sum(axis=1))
        A[:, 3:6, 0:3] = -A[:, 0:3, 3:6]
        A[:, 3:6, 3:6] = sw[:, None, None] * eye3
        g[:, 0:3] = np.cross(q, wr).sum(axis=1)
        g[:, 3:6] = wr.sum(axis=1)
    if K:
        A[:, n_pose:, n_pose:] = (w @ expression.DtD).reshape(n, K, K)
        g[:, n_pose:] = np.einsum("nha,hak->nk", np.einsum("nji,nhj->nhi", R, wr), D, optimize=True)
        if not fix_pose:
            wy = (w[..., None] * y).transpose(0, 2, 1)  # (n, 3, H)
            M = (wy @ D.reshape(H, 3 * K)).reshape(n, 3, 3, K)  # Σ w y_j D_lk
            cross = np.stack([M[:, 1, 2] - M[:, 2, 1], M[:, 2, 0] - M[:, 0, 2], M[:, 0, 1] - M[:, 1, 0]],
                             axis=1)  # Σ w [y]× D_m
            A[:, 0:3, 6:] = R @ cross
            A[:, 3:6, 6:] = R @ (w @ D.reshape(H, 3 * K)).reshape(n, 3, K)
            A[:, 6:, 0:6] = A[:, 0:6, 6:].transpose(0, 2, 1)
    return A, g


def _regularise(A: np.ndarray, n_pose: int, K: int, fix_pose: bool) -> None:
    """Keep every frame's A solvable, in place: a tiny ridge on the weights, and on the pose of a
    frame without 3 visible markers (which has none)."""
    if K:
        diag = np.einsum("npp->np", A)[:, n_pose:]
        A[:, n_pose:, n_pose:] += np.eye(K) * (1e-9 * diag.max(axis=1, initial=0.0) + 1e-300)[:, None, None]
    if not fix_pose:
        A[:, :6, :6] += np.eye(6) * 1e-12 * (1.0 + np.abs(A[:, :6, :6]).max(axis=(1, 2)))[:, None, None]


def _solve_active_set(A: np.ndarray, g: np.ndarray, C: np.ndarray, free: np.ndarray, n_pose: int, K: int):
    """The step δ of A δ = g with the weights outside ``free`` held; a weight at zero that the step
    would make negative leaves the set and that frame's system is solved again (only the frames
    whose set changed: with many examples most settle at once). Returns δ and the set."""
    step = _solve_active(A, g, free, n_pose)
    if not K:
        return step, free
    free = free.copy()
    again = np.arange(A.shape[0])
    for _ in range(K):
        out = free[again] & (C[again] <= 0) & (step[again, n_pose:] < 0)
        changed = out.any(axis=1)
        if not changed.any():
            break
        again, out = again[changed], out[changed]
        free[again] &= ~out
        step[again] = _solve_active(A[again], g[again], free[again], n_pose)
    return step, free


def _step_weights(C: np.ndarray, dc: np.ndarray, free: np.ndarray):
    """Take the step dc on the weights C, stopping each frame at its first weight to reach zero.

    Returns the step's share alpha per frame (the pose takes the same), the new weights and the
    free set without the weights that reached zero.
    """
    neg = free & (C > 0) & (C + dc < 0)
    ratio = np.where(neg, C / np.where(neg, C - (C + dc), 1.0), np.inf)
    alpha = np.minimum(1.0, ratio.min(axis=1, initial=np.inf))
    C = np.maximum(C + alpha[:, None] * dc, 0.0)
    hit = neg & (np.abs(C) <= 1e-12 + 0 * C)
    C[hit] = 0.0
    return alpha, C, free & ~hit


def _solve_active(A: np.ndarray, g: np.ndarray, free: np.ndarray, n_pose: int) -> np.ndarray:
    """Solve A δ = g per frame with the expression weights outside ``free`` held (δ = 0)."""
    n, P, _ = A.shape
    if free.size == 0 or free.all():
        M, rhs = A, g
    else:
        keep = np.concatenate([np.ones((n, n_pose), bool), free], axis=1)
        M = np.where(keep[:, :, None] & keep[:, None, :], A, 0.0)
        M[:, np.arange(P), np.arange(P)] = np.where(keep, np.einsum("npp->np", A), 1.0)
        rhs = np.where(keep, g, 0.0)
    try:
        return np.linalg.solve(M, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a degenerate frame (e.g. collinear markers)
        return np.stack([np.linalg.lstsq(M[i], rhs[i], rcond=None)[0] for i in range(n)])
