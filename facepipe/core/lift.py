"""Lifting 2D landmark tracks to 3D face motion: the mathematics (pure functions over arrays).

A tracked landmark l of frame f is the projection of a rig vertex through the camera:

    x_fl ≈ π(R_f (p_l + Σ_k c_fk D_kl) + t_f)

with p_l the landmark's rest position (head space), D_kl its displacement in the rig's example k,
c_f the expression weights (0 ≤ c ≤ c_max, a quadratic prior toward neutral), R_f, t_f the head
pose in the camera's coordinates and π the ideal pinhole projection (undistorted pixels).
:func:`fit_pose_expression_2d` fits pose and weights together by a robust (Cauchy), weighted
Levenberg–Marquardt, many frames at once. What the examples cannot explain stays as a 2D residual;
:func:`intersect_rays_triangles` puts each observed landmark back onto the fitted surface (the
ray from the camera centre through the observed pixel, met with the surface around the
landmark's vertex) — Fidaleo et al.'s non-rigid step, on the fitted face rather than the neutral
one. :func:`landmarks_to_handles` turns landmark displacements into handle displacements that
move those vertices alike through the rig's own shell matrix B.
"""

from __future__ import annotations

import numpy as np

from facepipe.core.camera import project
from facepipe.core.rigid import rotation_from_vector, skew

__all__ = ["fade_fill", "fit_pose_expression_2d", "intersect_ray_plane", "intersect_rays_triangles",
           "landmark_motion", "landmark_weights", "landmarks_to_handles", "robust_sigma", "rotation_from_vector",
           "soft_keep"]


def landmark_motion(basis: np.ndarray) -> np.ndarray:
    """(L,) how far each landmark moves across the examples: RMS over k of |D_kl| (rig units).

    A landmark that barely moves in any example is rigid (bridge of the nose, eye corners): the
    head pose rests on it. No hand-made list: the examples say it."""
    basis = np.asarray(basis, dtype=np.float64)
    if basis.shape[0] == 0:
        return np.zeros(basis.shape[1])
    return np.sqrt((basis ** 2).sum(axis=-1).mean(axis=0))


def landmark_weights(motion: np.ndarray, sigma_px: float, px_per_unit: np.ndarray, share: float = 0.1) -> np.ndarray:
    """Inverse variances (..., L) of the landmarks: noise σ² plus what the examples may miss.

    A landmark that moves by m in the examples is taken to be explained by them up to ``share`` × m
    (the part of an actor's motion there no example shows), so its variance is
    σ² + (share · m · px_per_unit)² — rigid points weigh most, as Fidaleo et al. weight them
    by hand.

    Parameters
    ----------
    motion : (L,) :func:`landmark_motion` in rig units.
    sigma_px : tracking noise (pixels).
    px_per_unit : (...,) pixels per rig unit at the face's depth (focal / depth).
    """
    scale = np.asarray(px_per_unit, dtype=np.float64)[..., None]
    return 1.0 / (sigma_px ** 2 + (share * np.asarray(motion, dtype=np.float64) * scale) ** 2)


def robust_sigma(residual: np.ndarray, visible: np.ndarray) -> float:
    """Per-coordinate noise σ of 2D residuals (..., L, 2) from the median residual length.

    For Gaussian noise of σ per coordinate the length |r| has median σ √(2 ln 2)."""
    e = np.linalg.norm(residual, axis=-1)[visible]
    if e.size == 0:
        return float("nan")
    return float(np.median(e) / np.sqrt(2.0 * np.log(2.0)))


def fit_pose_expression_2d(points: np.ndarray, base: np.ndarray, matrix: np.ndarray, rest: np.ndarray,
                           basis: np.ndarray, R: np.ndarray, t: np.ndarray, coeffs: np.ndarray | None = None, *,
                           upper: float = 1.0, prior: float | np.ndarray = 1.0, target: np.ndarray | None = None,
                           robust: float | None = None, iterations: int = 12, fix_pose: bool = False,
                           tolerance: float = 1e-6):
    """Fit head pose and bounded expression weights to each frame's 2D landmarks.

    Minimises, per frame f,

        Σ_l base_fl ρ(|π(R (p_l + Σ_k c_k D_kl) + t) − x_fl|) + Σ_k prior_k (c_k − target_fk)²

    over R, t and 0 ≤ c ≤ upper, with ρ(e) = e² (``robust`` None) or the Cauchy
    ρ(e) = s² ln(1 + e²/s²), s = ``robust`` pixels (a slipping landmark pulls little), by
    Levenberg–Marquardt on iteratively reweighted least squares. Bounds by an active set: a weight
    at a bound that the step would push past is held there, then steps are clipped. All frames
    are solved together (small dense systems, batched).

    Parameters
    ----------
    points : (n, L, 2) undistorted pixels (NaN where base is 0).
    base : (n, L) ≥ 0 inverse variances (0: missing).
    matrix : (3, 3) camera matrix.
    rest : (L, 3) landmark rest positions; basis : (K, L, 3) example displacements.
    R, t : (n, 3, 3), (n, 3) starting pose: camera = R @ head + t.
    coeffs : (n, K) starting weights (clipped into the bounds), default 0.
    prior : scalar or (K,) weight of the quadratic prior; target : (n, K) its centre (default 0,
        neutral).
    iterations : LM steps.
    fix_pose : fit the expression only.

    Returns
    -------
    R, t, coeffs, residual (n, L, 2) pixels of the fit, weights (n, L) the robust weights used
    last (base times the Cauchy factor).
    """
    x = np.where(np.isfinite(points), points, 0.0).astype(np.float64)
    base = np.asarray(base, dtype=np.float64)
    n, L = base.shape
    basis = np.asarray(basis, dtype=np.float64)
    K = basis.shape[0]
    R = np.array(R, dtype=np.float64)
    t = np.array(t, dtype=np.float64)
    C = np.zeros((n, K)) if coeffs is None else np.clip(np.array(coeffs, dtype=np.float64), 0.0, upper)
    prior = np.broadcast_to(np.asarray(prior, dtype=np.float64), (K,))
    target = np.zeros((n, K)) if target is None else np.asarray(target, dtype=np.float64)
    n_pose = 0 if fix_pose else 6
    basis_flat = basis.reshape(K, L * 3)
    basis_cols = basis.transpose(1, 2, 0)[None]  # (1, L, 3, K)

    q, X, r = _landmark_residual(x, matrix, rest, basis_flat, R, t, C)
    cost = _fit_cost(base, r, C, prior, target, robust)
    mu = np.full(n, 1e-3)
    # frames still converging: once a frame's step gains less than ``tolerance`` of its cost (or
    # the damping has grown hopeless) it is left alone, so the few slow ones do not cost the rest
    live = np.arange(n)
    for _ in range(iterations):
        if live.size == 0:
            break
        i = live
        Ri, ti, Ci, qi, Xi, ri = R[i], t[i], C[i], q[i], X[i], r[i]
        J = _residual_jacobian(_projection_jacobian(matrix, Xi), qi, Ri, basis_cols, n_pose)
        A, g = _normal_equations(J, _robust_weights(base[i], ri, robust), ri, Ci, prior, target[i], n_pose)
        free = np.concatenate([np.ones((len(i), n_pose), bool), ~_held_at_bounds(Ci, g[:, n_pose:], upper)], axis=1)
        step = _damped_step(A, g, free, mu[i])
        Rn, tn, Cn = _stepped(Ri, ti, Ci, step, n_pose, upper)
        qn, Xn, rn = _landmark_residual(x[i], matrix, rest, basis_flat, Rn, tn, Cn)
        cost_n = _fit_cost(base[i], rn, Cn, prior, target[i], robust)
        better = (cost_n <= cost[i]) & np.isfinite(cost_n) & (Xn[..., 2] > 0).all(axis=1)
        j = i[better]
        R[j], t[j], C[j], q[j], X[j], r[j] = Rn[better], tn[better], Cn[better], qn[better], Xn[better], rn[better]
        gain = np.where(better, cost[i] - cost_n, 0.0)
        cost[j] = cost_n[better]
        mu[i] = np.where(better, np.maximum(mu[i] / 3.0, 1e-7), np.minimum(mu[i] * 10.0, 1e7))
        done = (better & (gain <= tolerance * (1.0 + cost[i]))) | (mu[i] >= 1e4)
        live = i[~done]
    return R, t, C, r, _robust_weights(base, r, robust)


def _landmark_residual(x, matrix, rest, basis_flat, R, t, C):
    """The landmarks of weights C (m, K) posed by R, t: rotated q (m, L, 3), in the camera X = q + t,
    and the pixel residual of their projections against x (m, L, 2)."""
    y = rest + (C @ basis_flat).reshape(len(C), rest.shape[0], 3)
    q = y @ R.transpose(0, 2, 1)
    X = q + t[:, None, :]
    return q, X, project(matrix, X) - x


def _robust_weights(base, r, robust):
    """(m, L) weights of the residuals r (m, L, 2): base, times the Cauchy factor 1 / (1 + e²/s²)."""
    e2 = (r ** 2).sum(axis=-1)
    return base if robust is None else base / (1.0 + e2 / robust ** 2)


def _fit_cost(base, r, C, prior, target, robust):
    """(m,) the fitted cost: robust landmark terms plus the prior on the weights."""
    e2 = (r ** 2).sum(axis=-1)
    rho = e2 if robust is None else robust ** 2 * np.log1p(e2 / robust ** 2)
    return (base * rho).sum(axis=1) + (prior * (C - target) ** 2).sum(axis=1)


def _projection_jacobian(matrix, X):
    """dπ/dX (m, L, 2, 3) of the pinhole projection at camera points X (m, L, 3)."""
    fx, s, _ = matrix[0]
    fy = matrix[1, 1]
    zi = 1.0 / np.where(np.abs(X[..., 2]) > 1e-12, X[..., 2], 1e-12)
    Jp = np.zeros(X.shape[:-1] + (2, 3))
    Jp[..., 0, 0] = fx * zi
    Jp[..., 0, 1] = s * zi
    Jp[..., 0, 2] = -(fx * X[..., 0] + s * X[..., 1]) * zi * zi
    Jp[..., 1, 1] = fy * zi
    Jp[..., 1, 2] = -fy * X[..., 1] * zi * zi
    return Jp


def _residual_jacobian(Jp, q, R, basis_cols, n_pose):
    """(m, 2L, n_pose + K) derivatives of the residuals: by the rotation δθ (camera = exp(δθ) R y + t)
    and t unless the pose is fixed (``n_pose`` 0), then by each weight (R D_kl)."""
    m, L = q.shape[:2]
    K = basis_cols.shape[-1]
    parts = [-Jp @ skew(q), Jp] if n_pose else []
    if K:
        parts.append(Jp @ (R[:, None] @ basis_cols))
    return np.concatenate(parts, axis=-1).reshape(m, 2 * L, n_pose + K)


def _normal_equations(J, w, r, C, prior, target, n_pose):
    """Gauss–Newton system A δ = g of the weighted residuals, with the prior on the weights."""
    m, K = C.shape
    WJt = (J * np.repeat(w, 2, axis=1)[..., None]).transpose(0, 2, 1)
    A = WJt @ J
    g = -(WJt @ r.reshape(m, -1, 1))[..., 0]
    if K:
        prior_index = n_pose + np.arange(K)
        A[:, prior_index, prior_index] += prior
        g[:, n_pose:] -= prior * (C - target)
    return A, g


def _held_at_bounds(C, descent, upper):
    """(m, K) weights at a bound that the descent direction pushes past: held there this step."""
    return ((C <= 0.0) & (descent <= 0.0)) | ((C >= upper) & (descent >= 0.0))


def _damped_step(A, g, free, mu):
    """Levenberg–Marquardt step of (A + μ diag A) δ = g over the ``free`` unknowns (the others 0)."""
    diag = np.arange(A.shape[1])
    dA = A[:, diag, diag]
    M = np.where(free[:, :, None] & free[:, None, :], A, 0.0)
    M[:, diag, diag] = np.where(free, dA * (1.0 + mu[:, None]) + 1e-12 * (1.0 + dA.max(axis=1, keepdims=True)), 1.0)
    return np.linalg.solve(M, np.where(free, g, 0.0)[..., None])[..., 0]


def _stepped(R, t, C, step, n_pose, upper):
    """Pose and weights after a step: rotation vector and translation first (when fitted), then the
    weights, clipped into [0, upper]."""
    if n_pose:
        R = rotation_from_vector(step[:, :3]) @ R
        t = t + step[:, 3:6]
    return R, t, np.clip(C + step[:, n_pose:], 0.0, upper)


def intersect_rays_triangles(origins: np.ndarray, directions: np.ndarray, triangles: np.ndarray,
                             valid: np.ndarray | None = None, eps: float = 1e-12):
    """Nearest intersection of rays with sets of triangles (Möller–Trumbore), batched.

    Parameters
    ----------
    origins, directions : (..., 3) rays o + s d, s > 0 (d need not be unit).
    triangles : (..., N, 3, 3) N candidate triangles per ray (corners × xyz).
    valid : (..., N) bool, optional: padding triangles to ignore.

    Returns
    -------
    s : (...,) ray parameter of the nearest hit (inf where none); hit : (...,) bool;
    points : (..., 3) the hit points (NaN where none).
    """
    o = np.asarray(origins, dtype=np.float64)[..., None, :]
    d = np.asarray(directions, dtype=np.float64)[..., None, :]
    tri = np.asarray(triangles, dtype=np.float64)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = (e1 * p).sum(axis=-1)
    scale = np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1) * np.linalg.norm(d, axis=-1)
    ok = np.abs(det) > eps * np.maximum(scale, 1e-300)
    inv = 1.0 / np.where(ok, det, 1.0)
    tv = o - a
    u = (tv * p).sum(axis=-1) * inv
    qv = np.cross(tv, e1)
    v = (d * qv).sum(axis=-1) * inv
    s = (e2 * qv).sum(axis=-1) * inv
    tol = 1e-9
    inside = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (s > 0)
    if valid is not None:
        inside &= valid
    s = np.where(inside, s, np.inf)
    best = s.min(axis=-1)
    hit = np.isfinite(best)
    pts = np.where(hit[..., None], o[..., 0, :] + np.where(hit, best, 0.0)[..., None] * d[..., 0, :], np.nan)
    return best, hit, pts


def intersect_ray_plane(origins: np.ndarray, directions: np.ndarray, point: np.ndarray, normal: np.ndarray):
    """Intersection of rays (..., 3) with planes through ``point`` (..., 3) of ``normal`` (..., 3).

    Returns s (...,) (NaN for a ray parallel to the plane) and the points (..., 3)."""
    o, d = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
    den = (d * normal).sum(axis=-1)
    num = ((point - o) * normal).sum(axis=-1)
    ok = np.abs(den) > 1e-12 * np.linalg.norm(d, axis=-1) * np.linalg.norm(normal, axis=-1)
    s = np.where(ok, num / np.where(ok, den, 1.0), np.nan)
    return s, o + s[..., None] * d


def landmarks_to_handles(B_landmarks: np.ndarray, handle_edges: np.ndarray, smooth: float = 1.0,
                         ridge: float = 1e-2) -> np.ndarray:
    """(H, L) map from landmark displacements r to handle displacements δ through the rig's shell.

    The handle displacement that moves the landmark vertices by r through the shell (B_L δ ≈ r,
    B_L the rows of B at the landmark vertices), smooth over the rig's feature graph between the
    handles and small where no landmark feels it:

        δ = argmin |B_L δ − r|² + s (smooth |G δ|² + ridge |δ|²)

    with G the graph's edge differences and s the mean diagonal of B_Lᵀ B_L (so the constants are
    relative). Landmarks rarely sit where handles do, so B_L alone is ill-conditioned (a small
    residual would swing handles far): the graph term keeps neighbouring handles together, and the
    landmark motion B_L δ never exceeds r (‖B_L M‖₂ ≤ 1; on the ICT kit no handle moves by more than
    1.07 × the residual). A handle that no landmark feels moves only as its graph neighbours carry
    it (damped by the ridge); one that no path of edges joins to a felt handle does not move."""
    BL = np.asarray(B_landmarks, dtype=np.float64)
    H = BL.shape[1]
    edges = np.asarray(handle_edges, dtype=np.int64).reshape(-1, 2)
    G = np.zeros((len(edges), H))
    G[np.arange(len(edges)), edges[:, 0]] = 1.0
    G[np.arange(len(edges)), edges[:, 1]] = -1.0
    BtB = BL.T @ BL
    s = float(np.mean(np.diag(BtB))) + 1e-300
    return np.linalg.solve(BtB + s * (smooth * G.T @ G + ridge * np.eye(H)), BL.T)


def soft_keep(residual_sq: np.ndarray, known: np.ndarray, floor: np.ndarray, window: float) -> np.ndarray:
    """Factor (T, L) in [0, 1] keeping what of a residual stands out of what is expected anyway.

    ``floor`` (T, L) is the residual's expected mean square without a real expression behind it
    (noise, and what the rig's own model misses at a landmark); E, the residual's local mean square
    (a Gaussian window of ``window`` frames over the known samples), gives max(0, 1 − floor / E)
    — a Wiener-like shrink, local in time so an expression the examples lack, held for a while,
    comes through while noise and the model's small misfits do not."""
    from scipy.ndimage import gaussian_filter1d

    e = np.where(known, residual_sq, 0.0)
    k = known.astype(np.float64)
    if window > 0:
        e = gaussian_filter1d(e, window, axis=0, mode="nearest")
        k = gaussian_filter1d(k, window, axis=0, mode="nearest")
    E = e / np.maximum(k, 1e-12)
    return np.where(known & (E > 0), np.clip(1.0 - floor / np.maximum(E, 1e-300), 0.0, 1.0), 0.0)


def fade_fill(values: np.ndarray, known: np.ndarray, times: np.ndarray, decay: float) -> np.ndarray:
    """Fill unknown samples of (T, ...) series: linear interpolation between known neighbours,
    faded toward 0 (neutral) by exp(−d / decay) with d the time to the nearest known sample;
    before the first / after the last known sample the nearest value fades out likewise.

    Parameters
    ----------
    values : (T, M, ...) with anything where unknown; known : (T, M) bool; times : (T,) s.
    """
    values = np.array(values, dtype=np.float64)
    T = values.shape[0]
    flat = values.reshape(T, known.shape[1], -1)
    times = np.asarray(times, dtype=np.float64)
    for m in range(known.shape[1]):
        k = np.flatnonzero(known[:, m])
        miss = np.flatnonzero(~known[:, m])
        if miss.size == 0:
            continue
        if k.size == 0:
            flat[:, m] = 0.0
            continue
        tk = times[k]
        tm = times[miss]
        pos = np.searchsorted(tk, tm)
        before = np.clip(pos - 1, 0, k.size - 1)
        after = np.clip(pos, 0, k.size - 1)
        dist = np.minimum(np.abs(tm - tk[before]), np.abs(tk[after] - tm))
        for j in range(flat.shape[2]):
            interp = np.interp(tm, tk, flat[k, m, j])
            flat[miss, m, j] = interp * np.exp(-dist / decay)
    return flat.reshape(values.shape)
