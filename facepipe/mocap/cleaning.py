"""Cleaning a take with the rig's own prior: head pose, noise, outliers and gaps together.

The rig's example poses span the expressions the model knows (``model.example_handles``,
head-space handle positions of the rest pose and every example). A frame's markers are
explained as a rigid head motion of an expression in that span plus what the span misses:

    x_fm = R_f (r_m + Σ_k c_fk D_km + e_fm) + t_f + n_fm

with r the neutral handles (rest pose plus the actor's marker offsets), D_k the examples'
handle displacements, c ≥ 0 sparse expression weights, e the off-span part of the
expression (smooth in time, marker-dependent size τ_m) and n the capture noise (white,
size σ). Per frame, pose and weights are fitted together (Gauss–Newton with a non-negative
L1 prior on c, markers weighted by 1 / (σ² + τ_m²): skin that the examples explain well,
like the stable markers, counts most — Fidaleo et al.'s "rigid points weighted for pose",
measured rather than hand-picked). Then:

- **noise**: σ is measured from the second temporal differences of the residuals, τ_m
  from their size; a sample's off-span residual is kept with the factor τ_m² / (τ_m² + σ²)
  (a Wiener shrink: all of it when the examples cannot explain the marker, little of it when
  the residual is noise);
- **outliers**: a marker whose residual jumps away in one frame and back later (far beyond
  its own typical frame-to-frame step) is dropped for those frames and filled like a gap;
- **gaps**: a missing sample is the prior's prediction from that frame's visible markers plus
  the marker's residual interpolated across the gap (PCHIP) and faded out with the distance
  to the nearest visible sample: a short gap is a smooth interpolation, a long one follows
  the prior and, where nothing is known, decays to neutral;
- **frames without markers**: pose and weights are interpolated from the nearest fitted
  frames;
- optional temporal smoothing of the result (Gaussian, in frames).

Everything is arrays in, arrays and a JSON-serialisable report out.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from facepipe.mocap.gaps import fill_gaps
from facepipe.core.rigid import interpolate_poses, stable_marker_pose

__all__ = ["CleanOptions", "CleanResult", "clean_take", "find_jumps", "fit_pose_expression", "sample_counts",
           "noise_sigma", "rotation_from_vector"]


@dataclass
class CleanOptions:
    """Options of :func:`clean_take`.

    Attributes
    ----------
    prior : bool
        Use the rig's examples (False: only the rest pose, i.e. pose fitting, outliers and
        gap filling toward neutral).
    sparsity : float
        κ, in standard deviations of each expression weight: the L1 prior (threshold κ)
        chooses the active expressions, which are refitted without it and shrunk by the
        non-negative garrote max(0, 1 − κ² var / c²) (0: plain non-negative least squares).
    outlier : float
        A jump is a single-frame step of a marker's residual larger than this many times the
        marker's typical step (and than ``jump``) that is undone within ``max_jump`` seconds:
        the samples in between are outliers (see :func:`find_jumps`).
    jump : float or None
        Absolute floor of a jump (rig units); default 5 % of the marker spacing.
    max_jump : float
        Seconds a marker may stay jumped away and still be recognised.
    decay : float
        Seconds over which a marker's residual fades into a gap (the fill then follows
        the prior alone).
    short_gap : int
        Gaps up to this many frames are reported as interpolated, longer ones as filled
        from the prior.
    smooth : float
        σ (frames) of a Gaussian temporal smoothing of the cleaned handles; 0 is off.
    iterations : int
        Gauss–Newton iterations per pass.
    """

    prior: bool = True
    sparsity: float = 2.0
    outlier: float = 5.0
    jump: float | None = None
    max_jump: float = 1.0
    decay: float = 0.2
    short_gap: int = 5
    smooth: float = 0.0
    iterations: int = 12


@dataclass
class CleanResult:
    """What :func:`clean_take` returns.

    Attributes
    ----------
    head : (T, H, 3) float64
        Clean handle positions in head (rig) space, neutral at the reference, no NaN.
    R, t : (T, 3, 3), (T, 3)
        Head motion, world = R @ head + t.
    weights : (T, K) float64
        Expression weights of the examples.
    report : dict
        JSON-serialisable: ``markers`` (per marker counts), ``total``, ``noise``.
    outliers : (T, H) bool
        Samples dropped as outliers (and filled like gaps).
    """

    head: np.ndarray
    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    report: dict
    outliers: np.ndarray | None = None


def rotation_from_vector(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    a = np.linalg.norm(v, axis=-1)[..., None, None]
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    small = a < 1e-8
    s = np.where(small, 1.0, np.sin(a) / np.where(small, 1.0, a))
    c = np.where(small, 0.5, (1 - np.cos(a)) / np.where(small, 1.0, a * a))
    return np.eye(3) + s * K + c * (K @ K)


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
    T, H, _ = world.shape
    K = basis.shape[0]
    R = np.array(R, dtype=np.float64)
    t = np.array(t, dtype=np.float64)
    C = np.zeros((T, K)) if coeffs is None else np.maximum(np.array(coeffs, dtype=np.float64), 0.0)
    l1 = np.zeros((T, K)) if l1 is None else np.asarray(l1, dtype=np.float64)
    x = np.where(np.isfinite(world), world, 0.0)
    w_all = np.asarray(weights, dtype=np.float64).copy()
    D = basis.transpose(1, 2, 0)  # (H, 3, K)
    Dflat = D.reshape(H * 3, K)
    DtD = np.einsum("hak,hal->hkl", D, D).reshape(H, K * K)  # per marker D_mᵀ D_m
    n_pose = 0 if fix_pose else 6
    P = n_pose + K
    out_w = w_all.copy()
    eye3 = np.eye(3)
    for a in range(0, T, chunk):
        b = min(T, a + chunk)
        n = b - a
        Rc, tc, Cc, xc, w0, l1c = R[a:b], t[a:b], C[a:b], x[a:b], w_all[a:b], l1[a:b]
        allowed = np.ones((n, K), dtype=bool) if active is None else np.asarray(active[a:b], dtype=bool)
        Cc = np.where(allowed, Cc, 0.0)
        free = allowed.copy()
        w = w0
        for _ in range(iterations):
            y = reference + (Cc @ Dflat.T).reshape(n, H, 3)
            q = np.einsum("nij,nhj->nhi", Rc, y)
            r = xc - (q + tc[:, None, :])
            if robust_scale is not None:
                # Huber weights on the residual in units of the marker's scale, with the frame's
                # own robust scale as the floor: a jumping marker pulls less on pose and weights.
                # Huber, not a redescending (Cauchy, Tukey) loss: the problem stays convex, so
                # markers showing an expression the examples lack are not talked away
                u = np.linalg.norm(r, axis=-1) / robust_scale
                seen = w0 > 0
                med = np.nanmedian(np.where(seen, u, np.nan), axis=1, keepdims=True)
                c = 3.0 * np.maximum(np.nan_to_num(med, nan=1.0), 1.0)
                w = w0 * np.minimum(1.0, c / np.maximum(u, 1e-300))
            # normal equations A δ = g of the linearised problem, assembled from sums over
            # markers (J = [-[q]×, I, R D_m] is never formed): BLAS-sized products only
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
                A[:, n_pose:, n_pose:] = (w @ DtD).reshape(n, K, K)
                g[:, n_pose:] = np.einsum("nha,hak->nk", np.einsum("nji,nhj->nhi", Rc, wr), D, optimize=True)
                if not fix_pose:
                    wy = (w[..., None] * y).transpose(0, 2, 1)  # (n, 3, H)
                    M = (wy @ D.reshape(H, 3 * K)).reshape(n, 3, 3, K)  # Σ w y_j D_lk
                    cross = np.stack([M[:, 1, 2] - M[:, 2, 1], M[:, 2, 0] - M[:, 0, 2], M[:, 0, 1] - M[:, 1, 0]],
                                     axis=1)  # Σ w [y]× D_m
                    A[:, 0:3, 6:] = Rc @ cross
                    A[:, 3:6, 6:] = Rc @ (w @ D.reshape(H, 3 * K)).reshape(n, 3, K)
                    A[:, 6:, 0:6] = A[:, 0:6, 6:].transpose(0, 2, 1)
            if K:
                g[:, n_pose:] -= l1c
                # weights at zero whose gradient points inward come back into the set
                free |= (Cc <= 0) & (g[:, n_pose:] > 0) & allowed
                free &= (Cc > 0) | (g[:, n_pose:] > 0)
                diag = np.einsum("npp->np", A)[:, n_pose:]
                A[:, n_pose:, n_pose:] += np.eye(K) * (1e-9 * diag.max(axis=1, initial=0.0) + 1e-300)[:, None, None]
            if not fix_pose:
                # a frame without 3 visible markers has no pose: keep the system solvable
                A[:, :6, :6] += np.eye(6) * 1e-12 * (1.0 + np.abs(A[:, :6, :6]).max(axis=(1, 2)))[:, None, None]
            for _ in range(K + 1):
                step = _solve_active(A, g, free, n_pose)
                if not K:
                    break
                # a weight at zero that the step would make negative leaves the set; solve again
                out = free & (Cc <= 0) & (step[:, n_pose:] < 0)
                if not out.any():
                    break
                free &= ~out
            alpha = np.ones(n)
            if K:
                dc = step[:, n_pose:]
                neg = free & (Cc > 0) & (Cc + dc < 0)
                # stop at the first weight reaching zero
                ratio = np.where(neg, Cc / np.where(neg, Cc - (Cc + dc), 1.0), np.inf)
                alpha = np.minimum(1.0, ratio.min(axis=1, initial=np.inf))
                Cc = np.maximum(Cc + alpha[:, None] * dc, 0.0)
                hit = neg & (np.abs(Cc) <= 1e-12 + 0 * Cc)
                Cc[hit] = 0.0
                free &= ~hit
            if not fix_pose:
                Rc = rotation_from_vector(alpha[:, None] * step[:, :3]) @ Rc
                tc = tc + alpha[:, None] * step[:, 3:6]
        R[a:b], t[a:b], C[a:b], out_w[a:b] = Rc, tc, Cc, w
    return R, t, C, out_w


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


def noise_sigma(residual: np.ndarray, visible: np.ndarray) -> float:
    """Capture noise σ (per coordinate) from residual trajectories.

    White noise of σ gives second temporal differences of σ √6; the expression's own
    motion, already mostly removed from a residual, adds little. Robust (median absolute
    deviation), so outliers and the odd fast motion do not inflate it.

    Parameters
    ----------
    residual : (T, H, 3); visible : (T, H) bool.

    Returns
    -------
    float ≥ 0 (0 when fewer than 3 consecutive visible samples exist).
    """
    if residual.shape[0] < 3:
        return 0.0
    d2 = residual[2:] - 2 * residual[1:-1] + residual[:-2]
    ok = visible[2:] & visible[1:-1] & visible[:-2]
    vals = d2[ok]
    if vals.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(vals)) / np.sqrt(6.0))


def find_jumps(residual: np.ndarray, known: np.ndarray, floor: float, factor: float = 5.0,
               max_run: int = 30) -> np.ndarray:
    """Samples of each marker that jumped away and back: spikes and short plateaus.

    A jump is a single-frame step of a marker's residual trajectory (what the prior does not
    explain) that is large both absolutely (``floor``) and for that marker (``factor`` × its
    robust step scale: the median step length / 1.538, the median length of a 3D unit
    Gaussian), followed within ``max_run`` frames by a step back (the two steps nearly
    cancel). Both steps must be discontinuities (the steps just before and after them are
    small): a real expression the examples lack moves the residual continuously even when
    fast (a blink over 2–3 frames), and a marker that moves fast has large typical steps:
    neither is a jump. A one-frame spike is also found against the mean of its two
    neighbours, and a stretch of at most 2 frames cut off by the take's ends or a gap across
    one such step is an outlier too. A step without a return (a marker that stays moved) is
    left alone.

    Parameters
    ----------
    residual : (T, H, 3), NaN where unknown
    known : (T, H) bool
    floor : float, length units
    factor : float
    max_run : int, frames

    Returns
    -------
    (T, H) bool

    Example
    -------
    >>> r = np.zeros((9, 1, 3)); r[4, 0, 0] = 1.0
    >>> np.flatnonzero(find_jumps(r, np.ones((9, 1), bool), floor=0.1)[:, 0]).tolist()
    [4]
    """
    T, H = known.shape
    out = np.zeros((T, H), dtype=bool)
    if T < 3:
        return out
    step = residual[1:] - residual[:-1]  # (T-1, H, 3): step into frame t+1
    ok = known[1:] & known[:-1]
    size = np.where(ok, np.linalg.norm(np.nan_to_num(step), axis=-1), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        # per-coordinate scale: the median length of a 3D Gaussian step is 1.538 σ
        scale = np.nan_to_num(np.nanmedian(size, axis=0) / 1.538)
    thr = np.maximum(floor, factor * scale)  # (H,)
    big = ok & (np.nan_to_num(size) > thr)
    # one-frame spikes: the sample against the mean of its neighbours (a better signal-to-noise
    # than either step), and the neighbours agree with each other
    mid = residual[1:-1] - 0.5 * (residual[:-2] + residual[2:])
    ok3 = known[1:-1] & known[:-2] & known[2:]
    dev = np.where(ok3, np.linalg.norm(np.nan_to_num(mid), axis=-1), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dev_scale = np.nan_to_num(np.nanmedian(dev, axis=0) / 1.538)
    across = np.linalg.norm(np.nan_to_num(residual[2:] - residual[:-2]), axis=-1)
    dev = np.nan_to_num(dev)
    spike = ok3 & (dev > np.maximum(floor, factor * dev_scale)) & (across < 0.5 * dev)
    out[1:-1] |= spike
    # a short stretch cut off by the take's ends or a gap, across one big calm step
    edge = 2
    for m in np.flatnonzero(big.any(axis=0)):
        for a in np.flatnonzero(big[:, m]):
            calm = all(not ok[k, m] or size[k, m] < 0.25 * size[a, m] for k in (a - 1, a + 1) if 0 <= k < T - 1)
            if not calm:
                continue
            before = a + 1 - _run_start(known[:, m], a)  # known frames up to a
            after = _run_stop(known[:, m], a + 1) - (a + 1)
            if before <= edge < after:
                out[a + 1 - before:a + 1, m] = True
            elif after <= edge < before:
                out[a + 1:a + 1 + after, m] = True
    for m in np.flatnonzero(big.sum(axis=0) >= 2):
        ups = np.flatnonzero(big[:, m])
        used = np.zeros(ups.size, dtype=bool)
        for i, a in enumerate(ups):
            if used[i]:
                continue
            for j in range(i + 1, ups.size):
                b = ups[j]
                if b - a > max_run:
                    break
                sa, sb = step[a, m], step[b, m]
                na, nb = np.linalg.norm(sa), np.linalg.norm(sb)
                # a discontinuity, not a fast but continuous motion (a blink the examples lack):
                # the steps just before and after each jump are small
                around = [k for k in (a - 1, a + 1, b - 1, b + 1) if 0 <= k < T - 1 and k not in (a, b)]
                calm = all(not ok[k, m] or size[k, m] < 0.25 * min(na, nb) for k in around)
                if calm and np.linalg.norm(sa + sb) < 0.5 * max(na, nb):
                    out[a + 1:b + 1, m] = True  # frames a+1 .. b moved away
                    used[i] = used[j] = True
                    break
    return out


def _run_start(known: np.ndarray, t: int) -> int:
    """First frame of the run of known samples that contains frame t."""
    while t > 0 and known[t - 1]:
        t -= 1
    return t


def _run_stop(known: np.ndarray, t: int) -> int:
    """One past the last frame of the run of known samples that contains frame t."""
    while t < len(known) and known[t]:
        t += 1
    return t


def _runs(mask: np.ndarray):
    """Runs of True per column of a (T, M) mask: (column, start, stop) arrays."""
    step = np.diff(np.pad(mask.T.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    col, start = np.nonzero(step == 1)
    _, stop = np.nonzero(step == -1)
    return col, start, stop


def _distance_to_visible(known: np.ndarray) -> np.ndarray:
    """(T, M) frames from each sample to the nearest known sample of its marker (0 where known)."""
    T, M = known.shape
    idx = np.arange(T)[:, None]
    last = np.where(known, idx, -10 ** 9)
    last = np.maximum.accumulate(last, axis=0)
    nxt = np.where(known, idx, 10 ** 9)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    return np.minimum(idx - last, nxt - idx).astype(np.float64)


def clean_take(world: np.ndarray, reference: np.ndarray, basis: np.ndarray, stable: np.ndarray,
               times: np.ndarray, options: CleanOptions | None = None, *, fix_pose: bool = False,
               spacing: float = 1.0, names=None) -> CleanResult:
    """Head pose, expression weights and clean head-space handles of a take.

    Parameters
    ----------
    world : (T, H, 3) float
        Markers in the rig's units and (aligned) space, NaN where missing.
    reference : (H, 3)
        Neutral handles in head space (rest pose + the actor's marker offsets).
    basis : (K, H, 3)
        Example handle displacements from the rest pose (K may be 0).
    stable : (H,) bool
        Markers for the starting pose (all markers are used when fewer than 3 are visible).
    times : (T,) seconds, strictly increasing.
    options : CleanOptions
    fix_pose : bool
        The take is already in head space (no stabilisation): R = I, t = 0.
    spacing : float
        Typical marker spacing (rig units), the scale of the default jump threshold.
    names : list[str], optional
        Marker names for the report.

    Returns
    -------
    CleanResult
        ``head`` (T, H, 3): clean handles in head space, the neutral face at ``reference``
        (subtract the marker offsets ``reference - rest`` to drive the rig).
    """
    opt = options or CleanOptions()
    world = np.asarray(world, dtype=np.float64)
    T, H, _ = world.shape
    basis = np.asarray(basis, dtype=np.float64) if opt.prior else np.zeros((0, H, 3))
    K = basis.shape[0]
    names = [f"marker{m}" for m in range(H)] if names is None else list(names)
    times = np.asarray(times, dtype=np.float64)
    visible = np.isfinite(world).all(axis=-1)
    n_vis = visible.sum(axis=1)
    fps = 1.0 / np.median(np.diff(times)) if T > 1 else 30.0
    notes: list[str] = []

    # frames the fit can use: 3 markers fix a pose (1 is enough without one)
    usable = n_vis >= (1 if fix_pose else 3)
    if not usable.any():
        raise ValueError("no frame has enough visible markers")

    # starting pose: robust rigid fit of the stable markers, else of all markers
    if fix_pose:
        R0 = np.tile(np.eye(3), (T, 1, 1))
        t0 = np.zeros((T, 3))
    else:
        R0, t0 = stable_marker_pose(reference, world, stable, notes, usable,
                                    fallback="their starting pose comes from all visible markers")
        R0, t0, _ = interpolate_poses(np.where(usable[:, None, None], R0, np.nan),
                                      np.where(usable[:, None], t0, np.nan), times)

    rows = np.flatnonzero(usable)
    Wv = visible[rows].astype(np.float64)

    def fit_residual(R_rows, t_rows, C_rows):
        """(n, H, 3) the usable frames' markers in head space minus the model (missing markers at 0)."""
        head = np.einsum("nji,nhj->nhi", R_rows, np.where(visible[rows][..., None], world[rows], 0.0)
                         - t_rows[:, None, :])
        return head - (reference + np.einsum("nk,khc->nhc", C_rows, basis))

    # pass 1: unweighted, no sparsity: residuals for the noise and per-marker scales
    sigma_floor = 1e-7 * spacing  # noise-free input: keep the weights finite, the L1 bias negligible
    R1, t1, C1, _ = fit_pose_expression(world[rows], Wv, reference, basis, R0[rows], t0[rows],
                                        iterations=opt.iterations, fix_pose=fix_pose, robust_scale=sigma_floor)
    res1 = np.where(visible[rows][..., None], fit_residual(R1, t1, C1), np.nan)
    sigma = max(noise_sigma(np.nan_to_num(res1), visible[rows]), sigma_floor)
    # share of the noise the fit absorbs (parameters / equations), the rest stays in the residual
    absorbed = min(0.9, (6 * (not fix_pose) + K) / max(1.0, 3 * float(np.mean(n_vis[rows]))))
    jump = 0.05 * spacing if opt.jump is None else float(opt.jump)
    r2 = np.sum(res1**2, axis=-1)  # (n, H), NaN where missing
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        # per marker, per coordinate: first robustly (median |r|² / median of χ²(3)), so that a
        # marker that jumps or slides for a while cannot hide its bad samples by inflating its
        # own scale; then the mean over the samples that pass, which also counts the markers
        # that move off the examples' span only now and then
        ms = np.nan_to_num(np.nanmedian(r2, axis=0) / 2.366)
        rough = np.sqrt(sigma**2 + np.maximum(0.0, ms - sigma**2 * (1 - absorbed)))
        bad = (np.sqrt(np.nan_to_num(r2)) > opt.outlier * rough * np.sqrt(3.0)) & (np.sqrt(np.nan_to_num(r2)) > jump)
        ms = np.nan_to_num(np.nanmean(np.where(bad, np.nan, r2), axis=0) / 3.0)
    tau2 = np.maximum(0.0, ms - sigma**2 * (1 - absorbed))
    scale = np.sqrt(sigma**2 + tau2)  # per-coordinate residual scale of each marker
    trust = sigma**2 / (sigma**2 + tau2)  # relative weight of each marker in the fit

    # pass 2: weighted by trust, sparse expression, robust to jumping markers
    W = Wv * (trust / sigma**2)[None, :]
    l1 = None
    if K and opt.sparsity > 0:
        G = np.einsum("nh,khc->nk", W, basis**2)  # diag of Dᵀ W D per frame
        l1 = opt.sparsity * np.sqrt(G)
    R2, t2, C2, Wused = fit_pose_expression(world[rows], W, reference, basis, R1, t1, C1, l1=l1,
                                            iterations=opt.iterations, fix_pose=fix_pose,
                                            robust_scale=scale * np.sqrt(3.0))
    res2 = fit_residual(R2, t2, C2)
    res_seq = np.full((T, H, 3), np.nan)
    res_seq[rows] = np.where(visible[rows][..., None], res2, np.nan)
    known_seq = np.zeros((T, H), dtype=bool)
    known_seq[rows] = visible[rows]
    jumps = find_jumps(res_seq, known_seq, jump, opt.outlier, max_run=int(round(opt.max_jump * fps)))
    outlier_rows = jumps[rows]
    if outlier_rows.any():
        # refit without them (they were only down-weighted)
        W2 = np.where(outlier_rows, 0.0, W)
        if K and opt.sparsity > 0:
            l1 = opt.sparsity * np.sqrt(np.einsum("nh,khc->nk", W2, basis**2))
        R2, t2, C2, _ = fit_pose_expression(world[rows], W2, reference, basis, R2, t2, C2, l1=l1,
                                            iterations=opt.iterations, fix_pose=fix_pose,
                                            robust_scale=scale * np.sqrt(3.0))
        res2 = fit_residual(R2, t2, C2)

    if K and opt.sparsity > 0:
        # the L1 prior chose which expressions are active; refit them without its shrinkage
        W2 = np.where(outlier_rows, 0.0, W)
        R2, t2, C2, _ = fit_pose_expression(world[rows], W2, reference, basis, R2, t2, C2,
                                            iterations=opt.iterations, fix_pose=fix_pose,
                                            robust_scale=scale * np.sqrt(3.0), active=C2 > 0)
        # ... and shrink each by the non-negative garrote max(0, 1 - κ² var / c²): a weight of a
        # few standard deviations (a near-neutral frame) is pulled toward zero, a clear one is
        # left alone (the L1 prior would bias every active weight by κ standard deviations)
        var = 1.0 / np.maximum(np.einsum("nh,khc->nk", W2, basis**2), 1e-300)
        C2 = C2 * np.maximum(0.0, 1.0 - opt.sparsity**2 * var / np.maximum(C2**2, 1e-300))
        res2 = fit_residual(R2, t2, C2)

    # back to every frame: unusable frames get interpolated pose and weights
    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    C = np.zeros((T, K))
    R[rows], t[rows], C[rows] = R2, t2, C2
    empty = ~usable
    if empty.any():
        R, t, _ = interpolate_poses(R, t, times)
        for k in range(K):
            C[empty, k] = np.interp(times[empty], times[rows], C2[:, k])
    outlier = np.zeros((T, H), dtype=bool)
    outlier[rows] = outlier_rows
    known = visible & ~outlier
    residual = np.full((T, H, 3), np.nan)
    residual[rows] = np.where(known[rows][..., None], res2, np.nan)

    keep = tau2 / (tau2 + sigma**2)  # Wiener shrink of the off-span residual, per marker
    model = reference + np.einsum("tk,khc->thc", C, basis)
    # residual across gaps: PCHIP, faded with the distance to the nearest known sample
    never = ~known.any(axis=0)
    res_known = np.where(never[None, :, None], 0.0, residual)
    res_filled, _ = fill_gaps(res_known, times=times, marker_names=names)
    fade = np.exp(-_distance_to_visible(known) / max(opt.decay * fps, 1e-9))
    clean = model + keep[None, :, None] * fade[..., None] * res_filled
    if opt.smooth and opt.smooth > 0 and T > 1:
        from scipy.ndimage import gaussian_filter1d

        clean = gaussian_filter1d(clean, float(opt.smooth), axis=0, mode="nearest")

    # report
    per, total = sample_counts(~visible, outlier.sum(axis=0), int(empty.sum()), opt.short_gap, names, trust,
                               np.sqrt(3 * ms))
    report = {
        "markers": per,
        "total": total,
        "noise": {
            "sigma": float(sigma),
            "off_span_rms_median": float(np.median(np.sqrt(3 * tau2))) if H else 0.0,
            "residual_kept_median": float(np.median(keep)) if H else 0.0,
            "jump_threshold": float(jump),
            "examples": int(K),
            "active_expressions_mean": float((C > 0).sum(axis=1).mean()) if K and T else 0.0,
        },
        "smooth_frames": float(opt.smooth or 0.0),
        "notes": notes,
    }
    return CleanResult(clean, R, t, C, report, outlier)


def sample_counts(missing: np.ndarray, outliers: np.ndarray, frames_interpolated: int, short_gap: int, names,
                  weight: np.ndarray, residual_rms: np.ndarray) -> tuple[dict, dict]:
    """The cleaning report's per-marker and total counts.

    missing : (T, H) mask of missing samples; outliers : (H,) samples dropped per marker;
    frames_interpolated : frames whose pose was interpolated; short_gap : gaps up to this many
    frames count as interpolated, longer ones as filled from the prior; weight, residual_rms :
    (H,) each marker's weight in the fit and residual scale.
    """
    T, H = missing.shape
    col, start, stop = _runs(missing)
    run_len = stop - start
    gaps = np.bincount(col, minlength=H)
    longest = np.zeros(H, dtype=np.int64)
    np.maximum.at(longest, col, run_len)
    short_fill = np.zeros(H, dtype=np.int64)
    np.add.at(short_fill, col, np.where(run_len <= short_gap, run_len, 0))
    n_missing = missing.sum(axis=0)
    per = {names[m]: {"missing": int(n_missing[m]), "gaps": int(gaps[m]), "longest_gap": int(longest[m]),
                      "interpolated": int(short_fill[m]), "from_prior": int(n_missing[m] - short_fill[m]),
                      "outliers": int(outliers[m]), "weight": float(weight[m]),
                      "residual_rms": float(residual_rms[m])}
           for m in range(H)}
    total = {
        "frames": int(T),
        "markers": int(H),
        "missing": int(n_missing.sum()),
        "missing_fraction": float(missing.mean()) if T else 0.0,
        "gaps": int(gaps.sum()),
        "longest_gap": int(longest.max()) if H else 0,
        "longest_gap_marker": names[int(np.argmax(longest))] if H and longest.max() > 0 else None,
        "filled": int(n_missing.sum() + outliers.sum()),
        "interpolated": int(short_fill.sum()),
        "from_prior": int(n_missing.sum() - short_fill.sum()),
        "outliers": int(outliers.sum()),
        "frames_interpolated": int(frames_interpolated),
    }
    return per, total
