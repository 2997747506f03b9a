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
              names=None, prior: np.ndarray | None = None, iterations: int = 8):
    """Head motion from the visible stable markers, and the handles in head space.

    Parameters
    ----------
    handle_positions : (T, H, 3) world, NaN where a sample is missing.
    rest_handles : (H, 3); stable : (H,) bool.
    frames, names : frame numbers and marker names, for messages.
    prior : (E, H, 3) head-space handle positions of the rig's poses (rest first), or None.
        Stable markers still move a little with expressions (skin over the brow, temples);
        aligning them to the rest pose would read that motion as head motion. With a prior,
        the pose is estimated in turn: fit the rigid motion to where the expression (the
        prior's least-squares fit to all visible handles) puts the stable markers, reweight
        the stable markers by how well that explains them (Cauchy weights), re-fit.
    iterations : alternations of rigid fit and expression fit.

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
    targets = np.where(visible[..., None], pts, 0.0)
    weights = visible.astype(np.float64)
    reference = np.broadcast_to(rest_handles[stable], pts.shape)
    use_prior = prior is not None and len(prior) > 1
    for _ in range(iterations if use_prior else 1):
        R, t = rigid_fit(reference, targets, weights)
        head = np.einsum("tji,thj->thi", R, handle_positions - t[:, None, :])
        if not use_prior:
            break
        reference = expression_fit(head, rest_handles, prior)[:, stable]
        # iteratively reweighted: a stable marker the expression cannot explain (skin that
        # buckles, a marker knocked loose) is trusted less than the others in that frame
        predicted = np.einsum("tij,tsj->tsi", R, reference) + t[:, None, :]
        residual = np.linalg.norm(predicted - targets, axis=-1)
        scale = np.median(np.where(visible, residual, np.nan), axis=1, keepdims=True)
        scale = np.maximum(np.nan_to_num(scale), 1e-9 * (1.0 + np.abs(rest_handles).max()))
        weights = visible / (1.0 + (residual / scale) ** 2)
    return head, R, t


def expression_fit(head: np.ndarray, rest_handles: np.ndarray, prior: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """Least-squares fit of the prior's handle displacements to the visible handles, per frame.

    Parameters
    ----------
    head : (T, H, 3) head-space handles, NaN where missing.
    rest_handles : (H, 3); prior : (E, H, 3) poses, rest first.
    ridge : Tikhonov weight relative to the mean squared prior displacement, so a frame the
        prior cannot explain is pulled toward the rest pose rather than over-fitted.

    Returns
    -------
    (T, H, 3) the fitted handle positions (every handle, missing ones too).
    """
    D = (prior[1:] - rest_handles).reshape(len(prior) - 1, -1)  # (E', 3H)
    u = (head - rest_handles).reshape(head.shape[0], -1)  # (T, 3H)
    seen = np.isfinite(u)
    lam = ridge * float(np.mean(D**2)) * D.shape[1]
    out = np.empty_like(u)
    # frames sharing one visibility pattern share one solve (the common case: all visible)
    patterns, inverse = np.unique(seen, axis=0, return_inverse=True)
    for k, mask in enumerate(patterns):
        rows = np.flatnonzero(inverse.ravel() == k)
        Dm = D[:, mask]
        w = np.linalg.solve(Dm @ Dm.T + lam * np.eye(len(D)), Dm @ u[rows][:, mask].T)  # (E', n)
        out[rows] = (w.T @ D)
    return rest_handles + out.reshape(head.shape)
