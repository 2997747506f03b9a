"""Temporal smoothing of per-frame estimates with the amount chosen from the data.

A take's per-frame estimates (head pose, handle positions) are a smooth motion plus white
noise. The Whittaker smoother (Eilers 2003) — a discrete smoothing spline,

    z = argmin Σ_t w_t (y_t − z_t)² + λ Σ_t (Δᵈ z)_t²,

with Δᵈ the differences of order d, is the exact posterior mean of a d-fold integrated random walk
observed in white noise (a Rauch–Tung–Striebel smoother without the recursion): it needs no
window, so the first and last frames are estimated from the frames they have without padding,
reflection or a one-sided kernel's bias — a polynomial of degree < d is kept exactly up to the
take's ends. The order sets what a take's ends do where one side is missing: second differences
(d = 2) continue the motion there as a straight line, so a head that accelerates at the first frame
(nodding, turning) is biased there by more than the noise the smoother removes; d = 3, 4 follow
its curvature at the cost of more noise at the ends. λ, and d among the candidates, are chosen
per group of columns by generalised cross-validation (Craven & Wahba 1979): the smoother that best
predicts each sample from the others, so a still marker is smoothed hard, a fast one barely, and
noise-free input is left (nearly) alone.

Pure arrays; a banded solve per λ, O(T) per column.
"""

from __future__ import annotations

from functools import lru_cache
from math import comb

import numpy as np
from scipy.linalg import eigvals_banded, solveh_banded

__all__ = ["LAMBDAS", "noise_variance_share", "row_decay", "smooth_series", "whittaker"]

#: λ candidates for the cross-validation (frames⁴: λ ≈ (smoothing length in frames)⁴ / 16)
LAMBDAS = np.logspace(-2, 7, 37)


def _penalty_bands(T: int, order: int = 2) -> np.ndarray:
    """(order + 1, T) upper banded form of DᵀD, D the (T − order, T) difference matrix of that order."""
    c = np.array([(-1.0) ** (order - k) * comb(order, k) for k in range(order + 1)])
    ab = np.zeros((order + 1, T))
    rows = T - order  # row r of D has c at columns r..r+order
    if rows <= 0:
        return ab
    for k in range(order + 1):
        for lag in range(order + 1 - k):  # (DᵀD)[r+k, r+k+lag] += c[k] c[k+lag]
            ab[order - lag, k + lag:k + lag + rows] += c[k] * c[k + lag]
    return ab


@lru_cache(maxsize=8)
def _penalty_eigenvalues(T: int, order: int) -> np.ndarray:
    """DᵀD's eigenvalues (tr H = Σ 1 / (1 + λ μ)): O(T²), and the same for every smoothing of a take's
    T frames (poses, weights, residuals), so kept. Read-only."""
    mu = eigvals_banded(_penalty_bands(T, order), select="a")
    mu.setflags(write=False)
    return mu


def whittaker(y: np.ndarray, lam: float, order: int = 2) -> np.ndarray:
    """The Whittaker smoother of the columns of y (T, …) with penalty λ on the differences of that
    order (0, or too few frames for one difference: y itself)."""
    y = np.asarray(y, dtype=np.float64)
    T = y.shape[0]
    if T <= order or lam <= 0:
        return y.copy()
    ab = lam * _penalty_bands(T, order)
    ab[-1] += 1.0
    return solveh_banded(ab, y.reshape(T, -1)).reshape(y.shape)


def row_decay(lam: float, order: int) -> float:
    """r < 1 such that the hat matrix's entries fall off as |H_ts| ≲ r^|t − s| away from the diagonal.

    Inside the take a row of H solves the recurrence e_t + λ (−Δ)^d e = 0 (Δ the second
    difference); its solutions are z^t with 1 + λ (2 − z − 1/z)^d = 0, i.e. z + 1/z = 2 − μ for the
    d roots μ of μ^d = −1/λ. r is the largest |z| below 1 (the slowest decaying solution); the
    take's ends change the coefficients of these solutions, not how fast they decay."""
    mu = lam ** (-1.0 / order) * np.exp(1j * np.pi * (2 * np.arange(order) + 1) / order)
    b = 2.0 - mu
    root = np.sqrt(b * b - 4.0)
    z = np.concatenate([(b - root) / 2.0, (b + root) / 2.0])
    inside = np.abs(z)[np.abs(z) < 1.0]
    return float(inside.max()) if inside.size else 1.0


def noise_variance_share(T: int, lam: float, block: int = 512, order: int = 2) -> np.ndarray:
    """(T,) the variance of smoothed unit white noise at each frame: the diagonal of H Hᵀ = H², H the
    hat matrix (I + λ DᵀD)⁻¹ — Σ_j H_tj², the noise of every frame that reaches frame t.

    This, not the hat diagonal H_tt (the share of frame t's own noise, an upper bound since H's
    eigenvalues lie in [0, 1]), is the noise variance left in a smoothed value; both are larger at a
    take's ends than in its middle (about twice with second differences).

    H's rows by banded solves, ``block`` columns at a time, each on a window of the take around
    its columns: H's rows fall off geometrically (:func:`row_decay`), so beyond ``reach`` frames
    they are below double precision and the window's cut changes nothing that counts (the cut
    couples to the rows' values there through λ DᵀD, at most λ 4^d times their size, which the
    reach takes to 1e-17 of a row's peak). O(T · (block + reach)) time — O(T) for a given
    smoothing strength, where the whole take at once was O(T²) — and O(block · (block + reach))
    memory; a strength whose rows reach across the take is solved on the whole take.
    """
    if T <= order or lam <= 0:
        return np.ones(T)
    ab = lam * _penalty_bands(T, order)
    ab[-1] += 1.0
    r = row_decay(lam, order)
    amplification = 1.0 + lam * 4.0 ** order
    reach = T if r >= 1.0 - 1e-12 else int(np.ceil(np.log(1e-17 / amplification) / np.log(r))) + order
    out = np.zeros(T)
    for start in range(0, T, block):
        stop = min(T, start + block)
        lo, hi = max(0, start - reach), min(T, stop + reach)
        unit = np.zeros((hi - lo, stop - start))
        unit[np.arange(start - lo, stop - lo), np.arange(stop - start)] = 1.0
        # the principal window of the banded matrix: LAPACK leaves the band's unused corner alone
        columns = solveh_banded(ab[:, lo:hi], unit)  # H is symmetric: its columns are its rows
        out[start:stop] = np.sum(columns**2, axis=0)
    return out


def smooth_series(y: np.ndarray, groups: np.ndarray | None = None, lambdas: np.ndarray = LAMBDAS,
                  noise_var: np.ndarray | None = None, orders=(2,)):
    """Whittaker-smooth the columns of y (T, n), λ (and the penalty's order) chosen per group by
    generalised cross-validation.

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
    orders : candidate orders of the penalised differences (2: an integrated random walk, the
        ends extrapolated as straight lines; higher: the ends follow the motion's curvature).

    Returns
    -------
    z : (T, n) smoothed; lam : (groups,) the λ chosen per group (index order of ``np.unique(groups)``);
    noise_share : (groups,) tr(H) / T, the share of white noise that passes the chosen smoother;
    order : (groups,) int, the order chosen per group.
    """
    y = np.asarray(y, dtype=np.float64)
    T, n = y.shape
    groups = np.arange(n) if groups is None else np.asarray(groups)
    labels, g = np.unique(groups, return_inverse=True)
    G = len(labels)
    orders = [int(o) for o in orders if T >= o + 2]
    order_out = np.full(G, min(orders) if orders else 2, dtype=np.int64)
    if T < 4 or not orders:
        return y.copy(), np.zeros(G), np.ones(G), order_out
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
    for order in orders:
        mu = _penalty_eigenvalues(T, order)
        for lam in lambdas:
            zl = whittaker(y, lam, order)
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
                order_out[better] = order
    return z, lam_out, share, order_out
