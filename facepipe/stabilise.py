"""Head stabilisation: the rigid motion of the head from the stable markers.

The shell and the pose space work in head (rig) space; the head's rigid motion is taken
out of the markers before and put back on the output after.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
    """Least-squares rotation and translation with target ≈ R @ source + t (Kabsch), batched.

    Parameters
    ----------
    source : (N, 3) or (..., N, 3); target : (..., N, 3); weights : (..., N) ≥ 0 or None
        (a zero weight ignores a point, e.g. a missing marker).

    Returns
    -------
    R : (..., 3, 3) proper rotations; t : (..., 3).
    """
    target = np.asarray(target, dtype=np.float64)
    source = np.broadcast_to(np.asarray(source, dtype=np.float64), target.shape)
    if weights is None:
        weights = np.ones(target.shape[:-1])
    w = weights / np.maximum(weights.sum(axis=-1, keepdims=True), 1e-300)
    cs = np.einsum("...n,...nc->...c", w, source)
    ct = np.einsum("...n,...nc->...c", w, target)
    cov = np.einsum("...n,...ni,...nj->...ij", w, target - ct[..., None, :], source - cs[..., None, :])
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros(cov.shape)
    D[..., 0, 0] = 1
    D[..., 1, 1] = 1
    D[..., 2, 2] = d
    R = U @ D @ Vt
    t = ct - np.einsum("...ij,...j->...i", R, cs)
    return R, t


def stabilise(handle_positions: np.ndarray, rest_handles: np.ndarray, stable: np.ndarray, frames=None,
              names=None):
    """Head motion from the visible stable markers, and the handles in head space.

    Parameters
    ----------
    handle_positions : (T, H, 3) world, NaN where a sample is missing.
    rest_handles : (H, 3); stable : (H,) bool.
    frames, names : frame numbers and marker names, for messages.

    Returns
    -------
    head : (T, H, 3) handles in head (rig) space (NaN stays NaN); R : (T, 3, 3); t : (T, 3)
        with world = R @ head + t. Without 3 stable markers the take is taken as head space.
    """
    T = handle_positions.shape[0]
    if stable.sum() < 3:
        return handle_positions.copy(), np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3))
    pts = handle_positions[:, stable]
    visible = np.isfinite(pts).all(axis=-1)
    short = np.flatnonzero(visible.sum(axis=1) < 3)
    if len(short):
        frame = short[0] if frames is None else frames[short[0]]
        raise InputError(f"frame {frame}: fewer than 3 stable markers are visible ({len(short)} such frames); "
                         "the head's motion cannot be found",
                         hint="fill those markers, or mark more markers 'stable' in markers.csv")
    R, t = rigid_fit(rest_handles[stable], np.where(visible[..., None], pts, 0.0), visible.astype(np.float64))
    head = np.einsum("tji,thj->thi", R, handle_positions - t[:, None, :])
    return head, R, t
