"""Temporal smoothing of per-frame estimates with the amount chosen from the data.

A take's per-frame estimates (head pose, handle positions) are a smooth motion plus white
noise. The Whittaker smoother (Eilers 2003) — a discrete smoothing spline,

    z = argmin Σ_t w_t (y_t − z_t)² + λ Σ_t (z_{t−1} − 2 z_t + z_{t+1})²,

is the exact posterior mean of an integrated random walk observed in white noise (a
Rauch–Tung–Striebel smoother without the recursion): it needs no window, so the first and last
frames are estimated from the frames they have without padding, reflection or a one-sided
kernel's bias — a straight motion is kept exactly up to the take's ends. λ is chosen per group of
columns by generalised cross-validation (Craven & Wahba 1979): the λ that best predicts each
sample from the others, so a still marker is smoothed hard, a fast one barely, and noise-free
input is left (nearly) alone.

Pure arrays; a banded solve per λ, O(T) per column.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import eigvals_banded, solveh_banded

__all__ = ["LAMBDAS", "noise_variance_share", "smooth_series", "whittaker"]

#: λ candidates for the cross-validation (frames⁴: λ ≈ (smoothing length in frames)⁴ / 16)
LAMBDAS = np.logspace(-2, 7, 37)


def _penalty_bands(T: int) -> np.ndarray:
    """(3, T) upper banded form of DᵀD, D the (T−2, T) second-difference matrix."""
    d = np.zeros(T)
    c = np.array([1.0, -2.0, 1.0])
    for k in range(3):  # row r of D has c at columns r..r+2
        d[k:T - 2 + k] += c[k] ** 2
    e1 = np.zeros(T - 1)
    e1[0:T - 2] += c[0] * c[1]
    e1[1:T - 1] += c[1] * c[2]
    e2 = np.zeros(T - 2)
    e2[:] = c[0] * c[2]
    ab = np.zeros((3, T))
    ab[2] = d
    ab[1, 1:] = e1
    ab[0, 2:] = e2
    return ab


def whittaker(y: np.ndarray, lam: float) -> np.ndarray:
    """The Whittaker smoother of the columns of y (T, …) with penalty λ (0: y itself)."""
    y = np.asarray(y, dtype=np.float64)
    T = y.shape[0]
    if T < 3 or lam <= 0:
        return y.copy()
    ab = lam * _penalty_bands(T)
    ab[2] += 1.0
    return solveh_banded(ab, y.reshape(T, -1)).reshape(y.shape)


def noise_variance_share(T: int, lam: float, block: int = 512) -> np.ndarray:
    """(T,) the variance of smoothed unit white noise at each frame: the diagonal of H Hᵀ = H², H the
    hat matrix (I + λ DᵀD)⁻¹ — Σ_j H_tj², the noise of every frame that reaches frame t.

    This, not the hat diagonal H_tt (the share of frame t's own noise, an upper bound since H's
    eigenvalues lie in [0, 1]), is the noise variance left in a smoothed value; both are about twice
    as large at a take's ends as in its middle. H's rows by banded solves, ``block`` columns at a
    time: O(T²) time, O(T · block) memory.
    """
    if T < 3 or lam <= 0:
        return np.ones(T)
    ab = lam * _penalty_bands(T)
    ab[2] += 1.0
    out = np.zeros(T)
    for start in range(0, T, block):
        stop = min(T, start + block)
        unit = np.zeros((T, stop - start))
        unit[np.arange(start, stop), np.arange(stop - start)] = 1.0
        columns = solveh_banded(ab, unit)  # H is symmetric: its columns are its rows
        out[start:stop] = np.sum(columns**2, axis=0)
    return out


def smooth_series(y: np.ndarray, groups: np.ndarray | None = None, lambdas: np.ndarray = LAMBDAS,
                  noise_var: np.ndarray | None = None):
    """Whittaker-smooth the columns of y (T, n), λ chosen per group by generalised cross-validation.

    With ``noise_var`` (the known variance of each column's white noise, (n,) or a scalar), λ is
    chosen instead by the unbiased risk estimate (Mallows' C_p: rss / T − σ² + 2 σ² tr(H) / T),
    with λ = 0 (no smoothing) among the candidates: a series whose noise is small next to its
    own jumps and kinks is left as it is, which GCV (whose smallest λ still rounds a jump off)
    cannot choose.

    Parameters
    ----------
    y : (T, n) per-frame values.
    groups : (n,) int, columns that share a λ (e.g. a marker's three coordinates); default one
        group per column.
    lambdas : candidate λ (ascending).

    Returns
    -------
    z : (T, n) smoothed; lam : (groups,) the λ chosen per group (index order of ``np.unique(groups)``);
    noise_share : (groups,) tr(H) / T, the share of white noise that passes the chosen smoother.
    """
    y = np.asarray(y, dtype=np.float64)
    T, n = y.shape
    groups = np.arange(n) if groups is None else np.asarray(groups)
    labels, g = np.unique(groups, return_inverse=True)
    G = len(labels)
    if T < 4:
        return y.copy(), np.zeros(G), np.ones(G)
    mu = eigvals_banded(_penalty_bands(T), select="a")  # eigenvalues of DᵀD: tr H = Σ 1 / (1 + λ μ)
    count = np.bincount(g, minlength=G).astype(np.float64)
    z = y.copy()
    lam_out = np.zeros(G)
    share = np.ones(G)
    if noise_var is not None:  # C_p of λ = 0: rss = 0, tr H = T
        s2 = np.bincount(g, weights=np.broadcast_to(np.asarray(noise_var, dtype=np.float64), (n,)),
                         minlength=G) / count
        best = s2.copy()
    else:
        best = np.full(G, np.inf)
    for lam in lambdas:
        zl = whittaker(y, lam)
        rss = np.bincount(g, weights=((y - zl) ** 2).mean(axis=0), minlength=G)
        trace = float(np.sum(1.0 / (1.0 + lam * mu)))
        if noise_var is not None:
            gcv = rss / count - s2 + 2.0 * s2 * trace / T
        else:
            gcv = rss / count / (1.0 - trace / T) ** 2
        better = (gcv < best) & ~np.isclose(gcv, best, rtol=1e-12, atol=0.0)
        if better.any():
            best[better] = gcv[better]
            cols = better[g]
            z[:, cols] = zl[:, cols]
            lam_out[better] = lam
            share[better] = trace / T
    return z, lam_out, share
