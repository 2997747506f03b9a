"""Head stabilisation: the rigid motion of the head from the stable markers.

The shell and the pose space work in head (rig) space; the head's rigid motion is taken
out of the markers before and put back on the output after.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def _weighted_cross_covariance(source, target, weights):
    """The start of a weighted point-set fit (rigid or similarity), batched.

    Returns
    -------
    w : (..., N) weights normalised to sum 1; cs, ct : (..., 3) weighted centroids of source
    and target; xs : (..., N, 3) centred source; cov : (..., 3, 3) weighted cross-covariance
    of the centred target and source.
    """
    target = np.asarray(target, dtype=np.float64)
    source = np.broadcast_to(np.asarray(source, dtype=np.float64), target.shape)
    if weights is None:
        weights = np.ones(target.shape[:-1])
    w = weights / np.maximum(weights.sum(axis=-1, keepdims=True), 1e-300)
    cs = np.einsum("...n,...nc->...c", w, source)
    ct = np.einsum("...n,...nc->...c", w, target)
    xs = source - cs[..., None, :]
    cov = np.einsum("...n,...ni,...nj->...ij", w, target - ct[..., None, :], xs)
    return w, cs, ct, xs, cov


def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
    """Least-squares rotation and translation with target ≈ R @ source + t (Kabsch), batched.

    Parameters
    ----------
    source : (N, 3) or (..., N, 3); target : (..., N, 3); weights : (..., N) ≥ 0 or None
        (a zero weight ignores a point, e.g. a missing marker, whose coordinates must still be
        finite: 0 × NaN is NaN, so zero them).

    Returns
    -------
    R : (..., 3, 3) proper rotations; t : (..., 3).
    """
    _, cs, ct, _, cov = _weighted_cross_covariance(source, target, weights)
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros(cov.shape)
    D[..., 0, 0] = 1
    D[..., 1, 1] = 1
    D[..., 2, 2] = d
    R = U @ D @ Vt
    t = ct - np.einsum("...ij,...j->...i", R, cs)
    return R, t


def stable_marker_pose(reference: np.ndarray, world: np.ndarray, stable: np.ndarray, notes: list[str],
                       usable: np.ndarray | None = None, fallback: str = "head pose from all visible markers"):
    """Head pose per frame from the stable markers, from all markers where too few are seen.

    Parameters
    ----------
    reference : (H, 3) rest positions; world : (T, H, 3), NaN where missing.
    stable : (H,) bool, the rig's stable markers.
    notes : list[str], appended to when all markers stand in for the stable ones.
    usable : (T,) bool or None, the frames to fall back on all markers for (default every frame).
    fallback : how the note names the frames posed from all visible markers.

    Returns
    -------
    R : (T, 3, 3); t : (T, 3), NaN where no pose was found.
    """
    T = world.shape[0]
    if stable.sum() >= 3:
        R, t, _ = robust_rigid_fit(reference[stable], world[:, stable])
    else:
        R, t = np.full((T, 3, 3), np.nan), np.full((T, 3), np.nan)
        notes.append("fewer than 3 stable markers in the rig: the head pose comes from all markers")
    need = ~np.isfinite(t).all(axis=1)
    if usable is not None:
        need &= usable
    if need.any():
        Ra, ta, _ = robust_rigid_fit(reference, world[need])
        R[need], t[need] = Ra, ta
        if stable.sum() >= 3:
            notes.append(f"{int(need.sum())} frame(s) with fewer than 3 visible stable markers: {fallback}")
    return R, t


def similarity_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
    """Least-squares similarity target ≈ s R @ source + t (Umeyama 1991), batched.

    Parameters
    ----------
    source, target : (..., N, 3)
    weights : (..., N) ≥ 0 or None (zero ignores a point).

    Returns
    -------
    s : (...,) scale > 0; R : (..., 3, 3) proper rotations; t : (..., 3).

    Example
    -------
    >>> P = np.random.default_rng(0).normal(size=(6, 3))
    >>> s, R, t = similarity_fit(P, 2.5 * P + 1.0)
    >>> round(float(s), 6), np.allclose(R, np.eye(3)), np.allclose(t, 1.0)
    (2.5, True, True)
    """
    w, cs, ct, xs, cov = _weighted_cross_covariance(source, target, weights)
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(cov.shape[:-1])
    D[..., 2] = d
    R = U @ (D[..., :, None] * Vt)
    var = np.einsum("...n,...nc,...nc->...", w, xs, xs)
    s = (S * D).sum(axis=-1) / np.maximum(var, 1e-300)
    t = ct - s[..., None] * np.einsum("...ij,...j->...i", R, cs)
    return s, R, t


def robust_rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
                     iterations: int = 10, scale: float | None = None):
    """Rigid fit target ≈ R @ source + t that down-weights points that do not follow (IRLS).

    Iteratively reweighted Kabsch with Cauchy weights 1 / (1 + (r / c)²), where r is a
    point's residual and c = 2.5 × the frame's robust residual scale (1.4826 × median), but
    at least ``scale``: a marker that slid on the skin or jumped for a frame moves the pose
    little, while with every point consistent it is the plain least-squares fit.

    Parameters
    ----------
    source : (N, 3) or (T, N, 3); target : (T, N, 3), NaN allowed (ignored).
    weights : (T, N) prior weights ≥ 0 (e.g. visibility × per-marker trust), or None.
    iterations : reweighting rounds.
    scale : residual floor (length units) below which points are not down-weighted, so a
        noise-free frame is not reweighted by rounding error; default 1e-6 × the source's size.

    Returns
    -------
    R : (T, 3, 3); t : (T, 3); w : (T, N) the final weights (0 for missing points).
    Frames with fewer than 3 usable points get NaN (see :func:`interpolate_poses`).
    """
    target = np.asarray(target, dtype=np.float64)
    source = np.broadcast_to(np.asarray(source, dtype=np.float64), target.shape)
    ok = np.isfinite(target).all(axis=-1) & np.isfinite(source).all(axis=-1)
    base = ok.astype(np.float64) if weights is None else np.where(ok, weights, 0.0)
    # a missing point's coordinates are zeroed as well as its weight: in the fit's sums 0 × NaN is NaN
    src = np.where(ok[..., None], source, 0.0)
    tgt = np.where(ok[..., None], target, 0.0)
    if scale is None:
        scale = 1e-6 * (1.0 + float(np.abs(src).max(initial=0.0)))
    w = base.copy()
    empty = ~(base > 0).any(axis=-1, keepdims=True)
    for _ in range(max(1, iterations)):
        R, t = rigid_fit(src, tgt, w)
        r = np.linalg.norm(np.einsum("...ij,...nj->...ni", R, src) + t[..., None, :] - tgt, axis=-1)
        # the frame's median residual over its points; a frame without points gets 0 (so c is the
        # floor, and numpy has no empty slice to warn about)
        med = np.nanmedian(np.where(base > 0, r, np.where(empty, 0.0, np.nan)), axis=-1, keepdims=True)
        c = 2.5 * np.maximum(np.nan_to_num(1.4826 * med), scale)
        w = base / (1.0 + (r / c) ** 2)
    R, t = rigid_fit(src, tgt, w)
    few = (base > 0).sum(axis=-1) < 3
    R[few] = np.nan
    t[few] = np.nan
    return R, t, w


def interpolate_poses(R: np.ndarray, t: np.ndarray, times: np.ndarray | None = None):
    """Fill frames whose pose is NaN from the nearest known ones (slerp and linear; held at the ends).

    Parameters
    ----------
    R : (T, 3, 3) with NaN rows for unknown poses; t : (T, 3); times : (T,) or None.

    Returns
    -------
    R, t : filled copies; filled : (T,) bool, the frames filled.

    Raises
    ------
    ValueError
        No frame has a pose.
    """

    R = np.array(R, dtype=np.float64)
    t = np.array(t, dtype=np.float64)
    bad = ~(np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1))
    if not bad.any():
        return R, t, bad
    good = np.flatnonzero(~bad)
    if good.size == 0:
        raise ValueError("no frame has a pose")
    x = np.arange(len(R), dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    q = np.clip(x[bad], x[good[0]], x[good[-1]])
    if good.size == 1:
        R[bad] = R[good[0]]
        t[bad] = t[good[0]]
    else:
        R[bad] = Slerp(x[good], Rotation.from_matrix(R[good]))(q).as_matrix()
        for a in range(3):
            t[bad, a] = np.interp(q, x[good], t[good, a])
    return R, t, bad


def rotation_from_vector(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    a = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = a < 1e-8
    s = np.where(small, 1.0, np.sin(a) / np.where(small, 1.0, a))
    c = np.where(small, 0.5, (1 - np.cos(a)) / np.where(small, 1.0, a * a))
    return np.eye(3) + s * K + c * (K @ K)


def skew(q: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): skew(q) @ p = q × p."""
    K = np.zeros(q.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -q[..., 2], q[..., 1], -q[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = q[..., 2], -q[..., 1], q[..., 0]
    return K
